"""The paper's claim, tested: DQN and tabular Q-learning against the exact optimum on scenarios of
352, 792 and 100 800 states — env steps and seconds to 95 % / 99 %, final ratio, over seeds.

    python recipes/study.py                                    # paper, multilevel, large × 3 seeds
    python recipes/study.py 'scenarios=[paper]' 'seeds=[0]' 'learners=[qlearning]'
    python recipes/study.py "overrides.dqn=['algo.total_frames=50000']"

Each learner runs its default profile, composed as ``recipes/<learner>.py env=<scenario>`` composes
it; see ``irdrc.experiments.study``.
"""

from __future__ import annotations

from irdrc.experiments.app import recipe
from irdrc.experiments.study import check_study, run_study

main = recipe("study", run_study, check=check_study)

if __name__ == "__main__":
    main()
