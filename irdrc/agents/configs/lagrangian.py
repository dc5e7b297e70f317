"""The Lagrangian DQN's hyperparameters (MODEL.md § A): DQN's, the multiplier's and the final
policy search's."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

from irdrc.agents.configs.value import DEFAULT_NETWORK, OffPolicyConfig
from irdrc.core.checks import (
    INT,
    build,
    check_bool,
    check_choice,
    check_number,
    check_numbers,
    reject_unknown_keys,
)

OBJECTIVES = ("throughput", "avg_reward", "link_capacity")
"""What a constrained learner maximises (as ``irdrc.core.cmdp.OBJECTIVES``)."""


@dataclass(frozen=True)
class SearchConfig:
    """How the Lagrangian DQN's final policy is searched (the ``algo.*`` keys of the same names).

    Attributes:
        search_span: the search moves along the path by this factor in μ at a time.
        measure_envs, measure_steps, measure_burn_in, measure_max_blocks: each long-run
            measurement runs ``measure_envs`` chains for ``measure_burn_in`` steps, then blocks of
            ``measure_steps`` until two consecutive blocks agree (at most ``measure_max_blocks``).
        mix_steps: at most this many measurements (regula falsi on the log-odds) to find the
            final randomisation.
        confirm: re-measure the search's result on fresh random numbers and climb the path while
            that measurement is above the target; mix on the fresh numbers.
    """

    search_span: float = 4.0
    measure_envs: int = 128
    measure_steps: int = 1_500
    measure_burn_in: int = 1_000
    measure_max_blocks: int = 8
    mix_steps: int = 10
    confirm: bool = True

    def __post_init__(self) -> None:
        check_numbers(
            self,
            "algo.",
            (
                ("search_span", 1, math.inf, {}),
                ("measure_envs", 2, 10**7, INT),
                ("measure_steps", 1, 10**9, INT),
                ("measure_burn_in", 0, 10**9, INT),
                ("measure_max_blocks", 1, 10**6, INT),
                ("mix_steps", 0, 60, INT),
            ),
        )
        check_bool("algo.confirm", self.confirm)


LAGRANGIAN_KEYS = ("mu_init", "mu_lr", "mu_min", "mu_max", "cost_window_frames")
"""The multiplier's ``algo.*`` keys (beside DQN's and the search's)."""


def lagrangian_dqn() -> OffPolicyConfig:
    """The Lagrangian learner's own DQN profile (``LagrangianConfig.dqn``'s default)."""
    return OffPolicyConfig(
        num_envs=8,
        frames_per_batch=32,
        total_frames=80_000,
        init_random_frames=512,
        buffer_size=20_000,
        batch_size=256,
        updates_per_batch=4,
        reward_means=False,
        lr=5e-4,
        tau=0.01,
        reward_centering=0.0,
        network=DEFAULT_NETWORK,
        name="dqn_lagrangian",
    )


@dataclass(frozen=True)
class LagrangianConfig:
    """The Lagrangian DQN (``algo=dqn_lagrangian``): DQN's keys, the multiplier's and the search's.

    Attributes:
        dqn: the machinery's hyperparameters (every ``OffPolicyConfig`` key).
        target_miss: m*, miss detection ≤ this (the recipe's top-level ``target_miss``).
        objective: what is maximised (the recipe's top-level ``objective``).
        mu_init: the multiplier at the start.
        mu_lr: dual ascent rate in log space: at full relative error μ changes by a factor
            e^mu_lr per 1 000 env steps.
        mu_min, mu_max: the multiplier's bounds.
        cost_window_frames: the measured miss detection is missed / event over about this many
            recent env steps (exponential average).
        search: how the final policy is searched (``SearchConfig``).
    """

    dqn: OffPolicyConfig = field(default_factory=lagrangian_dqn)
    target_miss: float = 0.05
    objective: str = "throughput"
    mu_init: float = 1.0
    mu_lr: float = 1.0
    mu_min: float = 1e-3
    mu_max: float = 1e5
    cost_window_frames: int = 4_000
    search: SearchConfig = field(default_factory=SearchConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "target_miss", check_number("target_miss", self.target_miss, 0, 1))
        check_choice("objective", self.objective, OBJECTIVES)
        check_numbers(
            self,
            "algo.",
            (
                ("mu_lr", 0, math.inf, {}),
                ("mu_min", 0, math.inf, {"open_lo": True}),
                ("mu_max", 0, math.inf, {"open_lo": True}),
                ("mu_init", self.mu_min, self.mu_max, {}),
                ("cost_window_frames", 1, 10**12, INT),
            ),
        )
        if self.dqn.reward_means:
            raise ValueError(
                "algo.reward_means=true: the Lagrangian DQN learns two signals (reward and "
                "misses) and keeps each sample's own; set algo.reward_means=false"
            )

    @property
    def name(self) -> str:
        """The profile's name."""
        return self.dqn.name

    @classmethod
    def from_sections(
        cls,
        algo: Any,
        network: Any = None,
        target_miss: float = 0.05,
        objective: str = "throughput",
    ) -> LagrangianConfig:
        """From the ``algo`` mapping (DQN's keys, ``LAGRANGIAN_KEYS`` and the search's), the
        ``network`` mapping and the problem; unknown keys are refused."""
        data = dict(algo)
        search_keys = {f.name for f in fields(SearchConfig)}
        reject_unknown_keys(
            "algo.", data, OffPolicyConfig.keys() | set(LAGRANGIAN_KEYS) | search_keys
        )
        own = {k: data.pop(k) for k in LAGRANGIAN_KEYS if k in data}
        search = build(SearchConfig, {k: data.pop(k) for k in search_keys if k in data}, "algo.")
        own_dqn = lagrangian_dqn()
        dqn = OffPolicyConfig.from_sections(data, network, base=own_dqn)
        return cls(dqn=dqn, target_miss=target_miss, objective=objective, search=search, **own)
