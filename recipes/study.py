"""The paper's claim, tested: DQN and tabular Q-learning against the exact optimum as S grows.

On scenarios of 352, 792 and 100 800 states: env steps and seconds to 95 % / 99 %, final ratio,
over seeds.

    python recipes/study.py                                    # paper, multilevel, large × 3 seeds
    python recipes/study.py 'scenarios=[paper]' 'seeds=[0]' 'learners=[qlearning]'
    python recipes/study.py "overrides.dqn=['algo.total_frames=50000']"

Each learner runs its default profile, composed as ``recipes/<learner>.py env=<scenario>`` composes
it; see ``irdrc.recipes.study``.
"""

from irdrc.recipes import study
from irdrc.runs import app

if __name__ == "__main__":
    app.main(study)
