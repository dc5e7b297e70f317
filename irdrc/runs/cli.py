"""``irdrc`` command: ``irdrc RECIPE [overrides…]`` runs a recipe in this process, the same run as
``python recipes/RECIPE.py`` in a checkout; ``irdrc`` lists the recipes, each with what it does.
The recipes and their configs are part of the installed package, so the command works wherever
irdrc is installed."""

from __future__ import annotations

import importlib
import sys

from irdrc.core.checks import closest
from irdrc.runs.scenarios import scenario_purposes

RECIPES: dict[str, tuple[str, str]] = {
    "dqn": (
        "irdrc.recipes.dqn",
        "DQN from TorchRL parts, evaluated exactly against the optimum — the main job.",
    ),
    "online": (
        "irdrc.online.recipe",
        "One vehicle learning on the road from its own stream, with the price of learning counted "
        "exactly.",
    ),
    "solve": (
        "irdrc.recipes.solve",
        "The exact optimum: value iteration on the exact model, and exact metrics beside the "
        "baselines.",
    ),
    "evaluate": (
        "irdrc.recipes.evaluate",
        "A saved policy scored on any scenario: exactly, by Monte-Carlo, against that scenario's "
        "optimum.",
    ),
    "qlearning": (
        "irdrc.recipes.qlearning",
        "Vectorised tabular Q-learning: several learners, several scenarios in one batch, scored "
        "exactly.",
    ),
    "constrained": (
        "irdrc.recipes.constrained.recipe",
        "The design question, answered exactly: the most data subject to a miss-detection target.",
    ),
    "fleet": (
        "irdrc.recipes.fleet.recipe",
        "Multi-agent learners on a fleet of vehicles (MODEL.md § C), scored against the "
        "centralised optimum.",
    ),
    "sac": (
        "irdrc.recipes.shares.sac",
        "SAC on the radar share of each step (MODEL.md § D), scored exactly against the optimum "
        "over ρ.",
    ),
    "ppo": (
        "irdrc.recipes.shares.ppo",
        "PPO on the radar share of each step (MODEL.md § D), scored exactly against the optimum "
        "over ρ.",
    ),
    "figure2": (
        "irdrc.paper.figure2",
        "The paper's Figure 2 and its claims, regenerated against the exact optimum.",
    ),
    "tradeoff": (
        "irdrc.paper.tradeoff",
        "The radar/communication trade-off the paper only mentions (its claim 3), exactly.",
    ),
    "study": (
        "irdrc.recipes.study",
        "The paper's claim, tested: DQN and tabular Q-learning against the exact optimum as S "
        "grows.",
    ),
    "sweep": (
        "irdrc.recipes.sweep",
        "A grid of overrides, each point one run of a recipe, on Ray Tune (or executor=local).",
    ),
    "demo": (
        "irdrc.recipes.demo",
        "Demo: roll out the paper's baselines on a batch of envs and print MODEL.md's metrics.",
    ),
    "bench_online": (
        "irdrc.bench.online",
        "Benchmark: the learners on one stream, scored by the price of learning, on seeds and "
        "scenarios no tuning used.",
    ),
    "bench_robust": (
        "irdrc.bench.robust",
        "Benchmark: does DQN reach the exact optimum on seeds it was never tuned on, in every "
        "scenario?",
    ),
    "bench_dqn": (
        "irdrc.bench.dqn",
        "Benchmark: how fast each DQN profile trains, and how soon it reaches the exact optimum.",
    ),
    "bench_timeshare": (
        "irdrc.bench.timeshare",
        "Benchmark: every learner of the radar share against the exact optimum over ρ, on seeds "
        "no tuning used.",
    ),
    "bench_constrained": (
        "irdrc.bench.constrained",
        "Benchmark: does the Lagrangian DQN reach the exact constrained optimum, on every seed?",
    ),
    "bench_fleet": (
        "irdrc.bench.fleet",
        "Benchmark: multi-agent learners on a fleet against the exact centralised optimum and the "
        "baselines.",
    ),
    "bench_scale": (
        "irdrc.bench.scale",
        "Benchmark: the exact solver's time and peak memory against S, up to a million states.",
    ),
    "bench_env": (
        "irdrc.bench.env",
        "Benchmark: env steps per second of DFRCEnv for several batch sizes (medians of repeated "
        "runs).",
    ),
}
"""Every recipe: its module (what ``recipes/NAME.py`` hands ``irdrc.runs.app.main``) and what it
does, in one sentence (the first paragraph of that script's docstring)."""


def recipes() -> dict[str, str]:
    """The runnable recipes, each with what it does, in the order ``irdrc`` lists them."""
    return {name: what for name, (_, what) in RECIPES.items()}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the console script (and of ``python -m irdrc``)."""
    args = sys.argv[1:] if argv is None else argv
    known = recipes()
    if not args or args[0] in ("-h", "--help", "list"):
        print("usage: irdrc RECIPE [overrides ...]        e.g. irdrc solve env.p1.speed=1.0")
        print("       irdrc RECIPE --help                 what it does, with examples")
        print("       irdrc RECIPE [overrides ...] --cfg  its config.yaml, checked; runs nothing")
        print("       irdrc --version\n")
        width = max(map(len, known))
        for name, what in known.items():
            print(f"  {name:<{width}}  {what}")
        print("\nscenarios (env=NAME):")
        purposes = scenario_purposes()
        width = max(map(len, purposes))
        for name, purpose in purposes.items():
            print(f"  {name:<{width}}  {purpose}")
        print(f"  {'PATH.yaml':<{width}}  A scenario of your own, in their form (docs/CONFIG.md).")
        return 0
    if args[0] in ("-V", "--version"):
        from importlib.metadata import PackageNotFoundError, version

        try:
            print(f"irdrc {version('irdrc')}")
        except PackageNotFoundError:  # run from a checkout that pip never installed
            print("irdrc (not installed: pip install -e . installs it)")
        return 0
    name = args[0].replace("-", "_")
    if name not in known:
        near = closest(name, known)
        hint = f"did you mean {near}? " if near else ""
        print(
            f"irdrc: unknown recipe {args[0]!r}; {hint}recipes: {', '.join(known)}",
            file=sys.stderr,
        )
        return 2
    from irdrc.runs import app

    app.main(importlib.import_module(RECIPES[name][0]), args[1:])
    return 0  # app.main exits with the run's status


if __name__ == "__main__":
    sys.exit(main())
