"""``recipes/demo.py``: the paper's baselines rolled out on a batch of envs, MODEL.md's metrics of
each, by Monte-Carlo.

    python recipes/demo.py                       # paper scenario
    python recipes/demo.py env=ref_impl reward.r4=50 eval.mc_num_envs=4096
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from irdrc.core.checks import build, check_choice, check_list
from irdrc.core.params import Params
from irdrc.runs.compose import Composed
from irdrc.runs.sections import Eval, check_common, scenario_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "demo"
POLICIES = ("round_robin", "always_radar", "always_comm", "random")
"""The baselines a demo may roll out (``irdrc.core.policies``)."""


@dataclass(frozen=True)
class Config:
    """The demo's keys (``irdrc/conf/demo.yaml``)."""

    params: Params = scenario_field()
    eval: Eval = field(default_factory=Eval)
    policies: tuple[str, ...] = POLICIES
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_common(self)
        item = lambda key, p: check_choice(key, p, POLICIES)  # noqa: E731
        object.__setattr__(
            self, "policies", check_list("policies", self.policies, item, distinct=True)
        )
        for key in ("mc_episodes", "mc_num_envs"):
            value = getattr(self.eval, key)
            if not value:
                raise ValueError(
                    f"eval.{key}={'null' if value is None else value}: the demo is a Monte-Carlo rollout of "
                    "each policy, eval.mc_episodes episodes in batches of eval.mc_num_envs envs, "
                    "so both must be >= 1 (the exact metrics of a baseline: recipes/solve.py)"
                )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked (and the cost of the rollouts)."""
    cfg = build(Config, composed.cfg)
    cfg.eval.check_cost(cfg.params)
    return cfg


def run(cfg: Config, run: Run) -> int:
    """Evaluate each policy of ``cfg.policies`` and print the side-by-side table."""
    from irdrc.core import policies
    from irdrc.core.env import DFRCEnv
    from irdrc.core.evaluate import evaluate
    from irdrc.core.metrics import format_table

    run.threads(1)
    params = cfg.params
    made = {
        "round_robin": policies.round_robin,
        "always_radar": policies.always_radar,
        "always_comm": policies.always_comm,
        "random": lambda: policies.uniform_random(seed=cfg.seed),
    }
    rows, errs = {}, {}
    t0 = time.perf_counter()
    for i, name in enumerate(cfg.policies):
        env = DFRCEnv(params, batch_size=[cfg.eval.mc_batch], device=cfg.device, seed=cfg.seed + i)
        ev = evaluate(made[name]().to(env.device), env, episodes=cfg.eval.mc_episodes)
        rows[name], errs[name] = ev.metrics, ev.ci95
    steps = ev.steps * len(cfg.policies)
    print(f"scenario={run.scenario} p1.speed={params.env.p1.speed} r4={params.reward.r4}")
    print(f"{ev.episodes} episodes of {params.env.horizon} steps per policy (± = 95 % CI)\n")
    print(format_table(rows, errors=errs))
    print(f"\n{steps} env steps in {time.perf_counter() - t0:.1f} s")
    return 0
