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
from irdrc.fleet.exact import (
    ACCESS,
    PRINTED,
    FleetModel,
    FleetSpec,
    baselines,
    fleet_metrics,
    single_optima,
    value_iteration_fleet,
)


def main(argv: list[str] | None = None) -> None:
    """Parse the fleet's options, solve it exactly and print the comparison table."""
    ap = argparse.ArgumentParser(prog="python -m irdrc.fleet", description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=2)
    ap.add_argument("--channels", type=int, default=1)
    ap.add_argument("--access", choices=ACCESS, default="scheduled")
    ap.add_argument("--share", type=float, default=0.5)
    ap.add_argument("--p1-speed", type=float, default=0.1, help="env.p1.speed of every vehicle")
    ap.add_argument(
        "--learn",
        choices=("idqn",),
        help="also train independent DQN with parameter sharing (irdrc.agents.fleet_dqn) and "
        "score its decentralised policy exactly",
    )
    ap.add_argument("--reward", choices=("team", "own"), default="team", help="--learn: reward")
    ap.add_argument("--frames", type=int, default=500_000, help="--learn: vehicle steps")
    ap.add_argument(
        "--agent-index", action="store_true", help="--learn: each vehicle also sees its index"
    )
    ap.add_argument("--seed", type=int, default=0, help="--learn: seed")
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
    single = single_optima(model)
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
    print(f"{'policy':<32} {'vehicle':>7} " + " ".join(f"{c:>14}" for c in PRINTED))
    best = None
    for name, pol in policies.items():
        _, per = fleet_metrics(model, pol)
        for row in per:
            cells = " ".join(f"{row[c]:>14.4f}" for c in PRINTED)
            print(f"{name:<32} {row['vehicle']!s:>7} {cells}")
        fleet = per[-1]["avg_reward"]
        best = fleet if best is None else best
        print(f"{'':<32} {'':>7} fleet reward / the optimum's: {fleet / best:.4f}")
    if args.learn:
        from irdrc.agents import dqn, fleet_dqn

        scorer = fleet_dqn.FleetScorer(model)
        t0 = time.perf_counter()
        rec = fleet_dqn.train(
            spec,
            dqn.DQNConfig(total_frames=args.frames),
            seed=args.seed,
            scorer=scorer,
            reward=args.reward,
            agent_index=args.agent_index,
        )
        curve = ", ".join(
            f"{h['env_steps']}: {h['optimality_ratio']:.4f}" for h in rec.history[::4]
        )
        final = rec.history[-1]["optimality_ratio"]
        print(
            f"\nidqn ({args.reward} reward{', agent index' if args.agent_index else ''}, seed "
            f"{args.seed}, {args.frames} vehicle steps, "
            f"{time.perf_counter() - t0:.0f} s): the vehicles' greedy tables reach "
            f"{final:.4f} of the centralised optimum (exact); every 100 000 steps: {curve}"
        )


if __name__ == "__main__":
    main()
