"""``python -m irdrc.fleet``: the fleet's exact optimum beside MODEL.md § C's baselines (N copies
of the single-vehicle optimum, round-robin in phase and anti-phase, a sensing rotation) and
radar-always, per vehicle and for the fleet (the paper's vehicles).

    python -m irdrc.fleet                          # N = 2, one channel, scheduled access, share 0.5
    python -m irdrc.fleet --channels 2 --share 0
    python -m irdrc.fleet --access collision --p1-speed 1.0
"""

from __future__ import annotations

import argparse
import time

import torch

from irdrc.core.params import Params
from irdrc.core.solve import value_iteration
from irdrc.fleet.exact import (
    ACCESS,
    FleetModel,
    FleetSpec,
    baselines,
    fleet_metrics,
    value_iteration_fleet,
)

COLUMNS = (
    "avg_reward",
    "throughput",
    "miss_detection",
    "radar_fraction",
    "denial_rate",
    "drop_rate",
)


def main(argv: list[str] | None = None) -> None:
    """Parse the fleet's options, solve it exactly and print the comparison table."""
    ap = argparse.ArgumentParser(prog="python -m irdrc.fleet", description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=2)
    ap.add_argument("--channels", type=int, default=1)
    ap.add_argument("--access", choices=ACCESS, default="scheduled")
    ap.add_argument("--share", type=float, default=0.5)
    ap.add_argument("--p1-speed", type=float, default=0.1, help="env.p1.speed of every vehicle")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    try:
        spec = FleetSpec(
            vehicle=Params.from_overrides({"env.p1.speed": args.p1_speed}),
            vehicles=args.vehicles,
            channels=args.channels,
            access=args.access,
            share=args.share,
        )
        t0 = time.perf_counter()
        model = FleetModel(spec)
    except ValueError as err:
        raise SystemExit(f"error: {err}") from err
    sol = value_iteration_fleet(model)
    solve_s = time.perf_counter() - t0
    single = value_iteration(model.single).policy
    S = model.num_states
    policies = {
        "centralised optimum": sol.policy,
        **baselines(model, single),
        "always radar": torch.full((S,), 2**model.N - 1, dtype=torch.int64),
    }
    print(
        f"fleet: {model.N} vehicles, {spec.channels} channel(s), {spec.access} access, share "
        f"{spec.share:g}, p1.speed {args.p1_speed:g}: S = {S:,} joint states, value iteration "
        f"{sol.iterations} sweeps, {solve_s:.1f} s\n"
    )
    print(f"{'policy':<32} {'vehicle':>7} " + " ".join(f"{c:>14}" for c in COLUMNS))
    best = None
    for name, pol in policies.items():
        _, per = fleet_metrics(model, pol)
        for row in per:
            cells = " ".join(f"{row[c]:>14.4f}" for c in COLUMNS)
            print(f"{name:<32} {row['vehicle']!s:>7} {cells}")
        fleet = per[-1]["avg_reward"]
        best = fleet if best is None else best
        print(f"{'':<32} {'':>7} fleet reward / the optimum's: {fleet / best:.4f}")


if __name__ == "__main__":
    main()
