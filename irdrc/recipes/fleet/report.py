"""The fleet's runs, reported (MODEL.md § C): a fleet described in one line, its policies' exact
metrics per vehicle and for the fleet in one table, its joint policy as ``policy.csv``, and the
centralised optimum beside the baselines (``recipes/solve.py env=fleet``: what cooperation is
worth)."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from irdrc.core.checks import grouped
from irdrc.core.exact import value_iteration
from irdrc.core.metrics import RESOLUTION
from irdrc.core.states import decode_state
from irdrc.fleet.model import FleetModel
from irdrc.fleet.policies import baselines, single_optima
from irdrc.fleet.scorer import PRINTED, fleet_metrics
from irdrc.fleet.spec import FleetSpec
from irdrc.runs.results import atomic_write_text, clean_number, summary_dict

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

FLEET_ROW = (
    "fleet rows: reward, throughput and drops are sums over the vehicles per fleet step; miss "
    "detection, radar fraction and denial rate are over every vehicle's steps (ratios of sums)"
)


def differences(spec: FleetSpec) -> dict[str, list[Any]]:
    """The model keys whose values differ between the vehicles, each with every vehicle's value."""

    def flat(prefix: str, node: Any) -> dict[str, Any]:
        if isinstance(node, dict):
            return {
                k: v for key, sub in node.items() for k, v in flat(f"{prefix}{key}.", sub).items()
            }
        return {prefix[:-1]: node}

    per = [flat("", p.to_dict()) for p in spec.vehicle_params]
    return {k: [d.get(k) for d in per] for k in per[0] if len({repr(d.get(k)) for d in per}) > 1}


SLOW_EXACT_STATES = 500_000
"""Beyond this many joint states the description says that exact evaluations are slow (here one
policy's exact metrics took 3 s at 430 336 joint states, 5 s at 518 400, 14 s at 952 576 and
79 s at 1 982 464)."""


def describe(spec: FleetSpec, observe: str, model: FleetModel) -> str:
    """One line naming the fleet (and a second where its exact evaluations are slow)."""
    reach = "exact" if model.exact else "beyond the exact model: Monte-Carlo"
    differ = differences(spec)
    alike = (
        "vehicles alike"
        if not differ
        else "vehicles differ in " + ", ".join(f"{k}={v}" for k, v in differ.items())
    )
    slow = (
        "\n[fleet] every exact evaluation, the optimum's first, is a stationary distribution over "
        "these joint states (one linear solve): from several seconds to over a minute each at "
        "this size"
        if model.exact and model.num_states > SLOW_EXACT_STATES
        else ""
    )
    return (
        f"fleet: {spec.vehicles} vehicles ({alike}), {spec.channels} channel(s), {spec.access} "
        f"access, share {spec.share:g}, observe {observe}; {grouped(model.num_states)} joint states "
        f"({reach}){slow}"
    )


def format_rows(
    rows: dict[str, list[dict[str, Any]]], reference: float, reference_name: str = "reference"
) -> str:
    """The per-vehicle table: one line per vehicle and one for the fleet with its ratio to
    ``reference`` (named ``reference_name``)."""
    head = f"{'policy':<34} {'vehicle':>7} " + " ".join(f"{c:>14}" for c in PRINTED)
    lines = [head, "-" * len(head)]
    for name, per in rows.items():
        for row in per:
            cells = " ".join(f"{_cell(row.get(c, math.nan)):>14}" for c in PRINTED)
            label = name if row["vehicle"] == 1 else ""
            lines.append(f"{label:<34} {row['vehicle']!s:>7} {cells}")
        lines.append(
            f"{'':<34} {'':>7} fleet reward / {reference_name}: "
            f"{per[-1]['avg_reward'] / reference:.4f}"
        )
    undefined = any(_cell(r.get(c)) == "—" for per in rows.values() for r in per for c in PRINTED)
    notes = [FLEET_ROW] + (
        ["—: undefined (a denial rate without any comm step)"] if undefined else []
    )
    return "\n".join([*lines, *notes])


def _cell(x: float | None) -> str:
    """A table cell: 4 decimals, or — where the metric is undefined; a value below the exact
    solves' accuracy (``RESOLUTION``) is 0, not the "-0.0000" of a −4e-15."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "—"
    return f"{0.0 if abs(x) < RESOLUTION else x:.4f}"


STARVED_THROUGHPUT = 1e-3
"""A vehicle whose throughput (packets per step) is below this never sends: starved."""


def starvation(name: str, per: list[dict[str, Any]]) -> str | None:
    """One line naming the vehicles of ``per`` (each vehicle's row, then the fleet's) that never
    send, with their throughput and drop rate; None when every vehicle sends."""
    starved = [r for r in per[:-1] if float(r["throughput"]) < STARVED_THROUGHPUT]
    if not starved:
        return None
    who = ", ".join(str(r["vehicle"]) for r in starved)
    numbers = "; ".join(
        f"vehicle {r['vehicle']}: throughput {float(r['throughput']):.4f}, drop rate "
        f"{float(r['drop_rate']):.3f}"
        for r in starved
    )
    return (
        f"starvation: under {name}, vehicle{'s' if len(starved) > 1 else ''} {who} of "
        f"{len(per) - 1} never send{'' if len(starved) > 1 else 's'} ({numbers}); the fleet's "
        "reward is earned by the others"
    )


def clean_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``rows`` with every float made JSON-safe (``clean_number``: NaN as None)."""
    return [
        {k: (clean_number(v) if isinstance(v, float) else v) for k, v in r.items()} for r in rows
    ]


def exact_rows(model: FleetModel, policies: dict[str, Any]) -> dict[str, list[dict[str, Any]]]:
    """Each policy's exact per-vehicle and fleet metrics."""
    return {name: fleet_metrics(model, pol)[1] for name, pol in policies.items()}


def reference_policies(model: FleetModel, single_optimum: torch.Tensor) -> dict[str, Any]:
    """The baselines of MODEL.md § C and radar always, as exact joint policies."""
    S = model.num_states
    return {
        **baselines(model, single_optimum),
        "always radar": torch.full((S,), 2**model.N - 1, dtype=torch.int64),
    }


def solve_fleet(
    model_spec: tuple[FleetSpec, str], gamma: float, tol: float, max_iter: int, seed: int, run: Run
) -> dict[str, Any]:
    """The fleet's centralised optimum (value iteration over the joint state and the 2^N joint
    actions), exact per-vehicle and fleet metrics beside the baselines, and what cooperation is
    worth: the optimum against N independent single-vehicle optima. Writes policy.csv (joint state
    → joint action); returns the summary."""
    spec, observe = model_spec
    model = FleetModel(spec)
    model.check_exact()
    t0 = time.perf_counter()
    sol = value_iteration(model, gamma=gamma, tol=tol, max_iter=max_iter)
    single = single_optima(model, gamma=gamma)
    wall = time.perf_counter() - t0
    print(describe(spec, observe, model))
    print(
        f"value iteration over {2**model.N} joint actions: {sol.iterations} sweeps, {wall:.1f} s\n"
    )
    rows = exact_rows(
        model, {"centralised optimum": sol.policy, **reference_policies(model, single)}
    )
    optimum = rows["centralised optimum"][-1]["avg_reward"]
    print(format_rows(rows, optimum))
    copies = rows["N copies of the single optimum"][-1]["avg_reward"]
    worth = optimum - copies
    print(
        f"\ncooperation is worth {worth:+.4f} per fleet step: the centralised optimum "
        f"{optimum:.4f} against {spec.vehicles} independent single-vehicle optima {copies:.4f} "
        f"({copies / optimum:.4f} of the optimum)"
    )
    if model.N <= 4:
        write_joint_policy_csv(run.dir / "policy.csv", model, sol.policy)
    opt = fleet_metrics(model, sol.policy)[0]
    return summary_dict(
        method="optimal",
        scenario=run.scenario,
        seed=int(seed),
        env_steps=0,
        wall_seconds=wall,
        metrics=opt,
        optimal=opt,
        fleet=fleet_info(spec, observe, model),
        sweeps=sol.iterations,
        table={name: clean_rows(per) for name, per in rows.items()},
        cooperation={
            "optimum": optimum,
            "independent_optima": copies,
            "worth": worth,
            "independent_over_optimum": copies / optimum if optimum else None,
        },
    )


def fleet_info(spec: FleetSpec, observe: str, model: FleetModel) -> dict[str, Any]:
    """The fleet for a summary: its vehicles, channels, access, share, what each observes, its
    joint states, whether it is exact, and how its vehicles differ."""
    return {
        "vehicles": spec.vehicles,
        "channels": spec.channels,
        "access": spec.access,
        "share": spec.share,
        "observe": observe,
        "joint_states": model.num_states,
        "exact": model.exact,
        "per_vehicle": differences(spec),
    }


def write_joint_policy_csv(
    path: Path, model: FleetModel, policy: torch.Tensor, optimal: torch.Tensor | None = None
) -> None:
    """``policy.csv`` of a fleet: one row per joint state — r, w, each vehicle's d, c, v, m, each
    vehicle's action (0 comm, 1 radar) and, with ``optimal``, the centralised optimum's."""
    states = model.vehicle_states()  # [S, N]
    cols = decode_state(states.reshape(-1), model.spec.vehicle.env.factor_levels)
    cols = cols.reshape(states.shape[0], model.N, -1)
    own = [0, 1, *range(4, cols.shape[-1])]
    names = ["d", "c", "v", "m", "phase"][: len(own)]
    header = ["r", "w"] + [f"{n}{i + 1}" for i in range(model.N) for n in names]
    header += [f"action{i + 1}" for i in range(model.N)]
    blocks = [cols[:, 0, 2:4]] + [cols[:, i, own] for i in range(model.N)]
    bits = (policy.long()[:, None] >> torch.arange(model.N)) & 1
    blocks.append(bits)
    if optimal is not None:
        header += [f"optimal{i + 1}" for i in range(model.N)]
        blocks.append((optimal.long()[:, None] >> torch.arange(model.N)) & 1)
    table = torch.cat(blocks, 1).tolist()
    lines = [",".join(header)] + [",".join(map(str, row)) for row in table]
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


def single_tables(model: FleetModel, greedy: torch.Tensor) -> list[dict[str, int]]:
    """Each vehicle's action in every single-vehicle state (policy.csv beyond the exact model)."""
    S = model.single.num_states
    per = greedy.long().reshape(-1, S)
    cols = decode_state(torch.arange(S), model.spec.vehicle.env.factor_levels).tolist()
    names = ("d", "c", "r", "w", "v", "m", "phase")
    rows = []
    for s in range(S):
        row = dict(zip(names, cols[s], strict=False))
        for i in range(per.shape[0]):
            row[f"action{i + 1}" if per.shape[0] > 1 else "action"] = int(per[i, s])
        rows.append(row)
    return rows
