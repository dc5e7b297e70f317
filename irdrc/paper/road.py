"""The paper's Fig. 2(a) on one vehicle, its own setting: the learners of ``recipes/bench_online.py``
on the paper scenario, each from its own stream, against episodes — the greedy policy's exact value,
and beside it the cumulative regret and missed events — and claim 1 (1a–1c) checked on them.

    python -m irdrc.paper.road outputs/bench_online          # docs/ONLINE.md and its figure

It reads a benchmark's run directory (the runs of the paper scenario in ``runs/``), draws
``docs/figures/fig2a_one_vehicle.png`` and fills the ``fig2a_one_vehicle`` block of the document
with the claims table and the commands that made it.
"""

from __future__ import annotations

import json
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from irdrc.core.exact import exact_scorer, stationary_metrics
from irdrc.core.params import Params
from irdrc.online.figures import plot_learners
from irdrc.paper.claims import Verdict, claim1, format_claims
from irdrc.paper.docs import replace_block, run_command
from irdrc.runs.results import atomic_write_text, measured_line

BLOCK = "fig2a_one_vehicle"
FIGURE = Path("docs/figures/fig2a_one_vehicle.png")
ORDER = ("posterior", "dqn", "dqn_paper", "qlearning", "qlearning_paper")
"""The learners drawn, in this order, where the benchmark ran them."""


def paper_histories(bench_dir: Path) -> dict[str, list[list[dict[str, Any]]]]:
    """Learner → the evaluation rows of each of its runs on the paper scenario."""
    out: dict[str, list[list[dict[str, Any]]]] = {}
    for path in sorted((Path(bench_dir) / "runs").glob("*__paper__*.json")):
        learner = path.name.split("__")[0]
        if learner in ORDER and "__m" not in path.name:
            out.setdefault(learner, []).append(json.loads(path.read_text())["history"])
    return {k: out[k] for k in ORDER if k in out}


def verdicts(histories: dict[str, list[list[dict[str, Any]]]], params: Params) -> list[Verdict]:
    """Claim 1 on one vehicle: the learners' final greedy policies' episode rewards (mean over
    runs), the first episode at which their mean curve reaches 95 % of the optimum, against the
    optimum's and round-robin's exact episode rewards."""
    scorer = exact_scorer(params)
    T = params.env.horizon
    opt = scorer.optimal_metrics.avg_reward * T
    rr = stationary_metrics(scorer.model, "round_robin").avg_reward * T
    final, to95 = {}, {}
    for name, runs in histories.items():
        final[name] = statistics.mean(h[-1]["optimality_ratio"] for h in runs) * opt
        mean = [
            statistics.mean(c)
            for c in zip(*[[r["optimality_ratio"] for r in h] for h in runs], strict=False)
        ]
        x = [r["episodes"] for r in runs[0]]
        to95[name] = next((e for e, m in zip(x, mean, strict=False) if m >= 0.95), None)
    return claim1(opt, rr, final, to95)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m irdrc.paper.road BENCH_DIR [DOC]``: the figure and the claims block."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        print(__doc__)
        return 2
    bench = Path(args[0])
    doc = Path(args[1]) if len(args) > 1 else Path("docs/ONLINE.md")
    histories = paper_histories(bench)
    if not histories:
        print(f"error: {bench} holds no run of the paper scenario (runs/*__paper__*.json)")
        return 2
    runs = {k: len(v) for k, v in histories.items()}
    title = "Fig. 2(a) on one vehicle (paper scenario): " + ", ".join(
        f"{k} ×{n}" for k, n in runs.items()
    )
    plot_learners(histories, FIGURE, title)
    table = format_claims(verdicts(histories, Params()))
    body = (
        "```bash\n"
        f"{run_command(bench)}\n"
        f"python -m irdrc.paper.road {bench}\n"
        "```\n\n"
        f"![Fig. 2(a) on one vehicle]({Path('figures') / FIGURE.name})\n\n"
        f"{table}\n\n{measured_line()}"
    )
    atomic_write_text(doc, replace_block(doc.read_text(), BLOCK, body))
    print(f"wrote {FIGURE} and the {BLOCK} block of {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
