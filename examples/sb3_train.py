"""A Stable-Baselines3 learner on the single-vehicle gymnasium id ``irdrc/DFRC-v0``, scored exactly.

SB3's DQN on the binary env (comm or radar each step) or its SAC on the radar share
(``env.actions=continuous``), with SB3's own defaults; the greedy policy is then scored exactly
against the scenario's optimum (``DFRCGymEnv.score``) and written as a ``policy.csv`` that
``recipes/evaluate.py policy=…`` reads, beside SB3's own ``progress.csv``:

    python examples/sb3_train.py --algo dqn --steps 50000 --out outputs/sb3_dqn env.p1.speed=0.5
    python recipes/evaluate.py policy=outputs/sb3_dqn/policy.csv env.p1.speed=0.5
    python examples/sb3_train.py --algo sac --steps 5000 --out outputs/sb3_sac
    python examples/sb3_train.py --steps 50000 --out outputs/sb3_ml env=multilevel reward.r4=50
    python recipes/evaluate.py policy=outputs/sb3_sac/policy.csv env.actions=continuous
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch
from stable_baselines3 import DQN, SAC
from stable_baselines3.common.logger import configure

import irdrc  # registers irdrc/DFRC-v0
from irdrc.core.gym import DFRCGymEnv
from irdrc.runs.tables import write_policy_csv


def natural(text: str) -> int:
    """An integer ≥ 0 (argparse's type)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} is not an integer >= 0")
    return value


def parse() -> argparse.Namespace:
    """The command line: learner, budget, seed, output folder, ``env.*`` / ``reward.*`` keys."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--algo", choices=("dqn", "sac"), default="dqn")
    p.add_argument("--steps", type=natural, default=50_000, help="env steps of training")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="outputs/sb3", help="folder for policy.csv and score.json")
    p.add_argument(
        "overrides",
        nargs="*",
        help="env=SCENARIO (irdrc/scenarios/), env.KEY=VALUE or reward.KEY=VALUE",
    )
    args = p.parse_args()
    if any("=" not in o for o in args.overrides):
        p.error(f"overrides are KEY=VALUE; got {[o for o in args.overrides if '=' not in o]}")
    pairs = (o.split("=", 1) for o in args.overrides)
    args.overrides = {k: json.loads(v) if v[:1] in "0123456789-[{" else v for k, v in pairs}
    if args.algo == "dqn" and args.overrides.get("env.actions") == "continuous":
        p.error(
            "DQN acts on discrete actions: env.actions=binary or levels (--algo sac: the share)"
        )
    return args


def main() -> None:
    args = parse()
    torch.set_num_threads(1)
    overrides = dict(args.overrides)
    if args.algo == "sac":
        overrides["env.actions"] = "continuous"  # SAC acts on the radar share ρ ∈ [0, 1]
    # a named scenario of irdrc/scenarios/, these keys on top
    scenario = overrides.pop("env", "paper")
    env = gymnasium.make("irdrc/DFRC-v0", params=irdrc.scenario(scenario, overrides))
    learner = DQN if args.algo == "dqn" else SAC
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    model = learner("MlpPolicy", env, seed=args.seed, verbose=0)
    model.set_logger(configure(str(out), ["csv"]))  # SB3's progress.csv beside the score
    start = time.time()
    model.learn(args.steps)
    seconds = time.time() - start

    def greedy(obs: np.ndarray) -> np.ndarray:
        return model.predict(obs, deterministic=True)[0]

    base = env.unwrapped  # gymnasium types it as a plain Env: narrowed to irdrc's own
    assert isinstance(base, DFRCGymEnv)
    score = base.score(greedy)
    table = base.policy_table(greedy)
    params = base.params
    # comm/radar actions (binary), else the radar share of each state (levels: level / (G − 1))
    shares = None if params.env.actions == "binary" else ()
    write_policy_csv(out / "policy.csv", table, params.env.factor_levels, shares=shares)
    result = {**score, "algo": args.algo, "steps": args.steps, "seed": args.seed}
    result["seconds"] = round(seconds, 1)
    record = {**result, "scenario": scenario, "overrides": overrides}
    (out / "score.json").write_text(json.dumps(record, indent=1))
    print(f"SB3 {args.algo}: {score['ratio']:.4f} of the optimum (exact) after {args.steps} steps")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
