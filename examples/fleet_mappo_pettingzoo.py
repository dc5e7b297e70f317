"""MAPPO on the fleet through PettingZoo, written as a user of another MARL library would: the fleet's
PettingZoo ``ParallelEnv`` (``irdrc.fleet.parallel_env``) under TorchRL's own ``PettingZooWrapper``,
trained with TorchRL's multi-agent parts as in TorchRL's MAPPO tutorial, then scored exactly against
the centralised optimum (``FleetParallelEnv.score``).

    python examples/fleet_mappo_pettingzoo.py --frames 40000 --seed 0 env.share=0.5 env.channels=1

Prints the exact ratio and writes it, with the greedy table, to ``--out`` (JSON).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import PettingZooWrapper
from torchrl.modules import MultiAgentMLP, ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from irdrc.fleet import parallel_env


def positive(text: str) -> int:
    """An integer ≥ 1 (argparse's type)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not an integer >= 1")
    return value


def parse() -> argparse.Namespace:
    """The command line: budget, seed, output, and ``env.*`` / ``reward.*`` overrides."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=positive, default=40_000, help="fleet steps in all")
    p.add_argument("--frames-per-batch", type=positive, default=1_000, help="fleet steps a rollout")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="a JSON file for the result")
    p.add_argument("overrides", nargs="*", help="env.KEY=VALUE or reward.KEY=VALUE")
    args = p.parse_args()
    if args.frames < args.frames_per_batch:
        p.error(f"--frames={args.frames} is less than one rollout (--frames-per-batch)")
    if any("=" not in o for o in args.overrides):
        p.error(f"overrides are KEY=VALUE; got {[o for o in args.overrides if '=' not in o]}")
    args.overrides = {
        k: json.loads(v) if v[:1] in "0123456789-[{" else v
        for k, v in (o.split("=", 1) for o in args.overrides)
    }
    if args.overrides.pop("env", "fleet") != "fleet":
        p.error(
            "this example runs the fleet (irdrc/scenarios/fleet.yaml): env=fleet, its keys on top"
        )
    return args


def main() -> None:
    args = parse()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    fleet = parallel_env(rewards="team", seed=args.seed, **args.overrides)
    if not fleet.model.exact:  # the result is scored exactly: refused before training, not after
        raise SystemExit(
            f"error: {fleet.model.num_states:,} joint states: this example scores "
            "its result exactly (env.vehicles=2 on the paper's sizes; "
            "irdrc.fleet.evaluate scores larger fleets by Monte-Carlo)"
        )
    agents = fleet.possible_agents
    env = PettingZooWrapper(fleet, group_map={"agents": agents}, return_state=True)
    n, width = len(agents), env.observation_spec["agents", "observation"].shape[-1]
    top = torch.as_tensor(fleet.observation_space(agents[0]).high).clamp(min=1.0)

    class Scale(nn.Module):  # observations to [0, 1]
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x / top

    def mlp(out: int, centralised: bool) -> nn.Module:
        return nn.Sequential(
            Scale(),
            MultiAgentMLP(
                n_agent_inputs=width,
                n_agent_outputs=out,
                n_agents=n,
                centralised=centralised,
                share_params=True,
                depth=2,
                num_cells=64,
                activation_class=nn.Tanh,
            ),
        )

    actor = ProbabilisticActor(
        TensorDictModule(mlp(2, False), [("agents", "observation")], [("agents", "logits")]),
        in_keys={"logits": ("agents", "logits")},
        out_keys=[("agents", "action")],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        log_prob_key=("agents", "action_log_prob"),
    )
    critic = TensorDictModule(
        mlp(1, True), [("agents", "observation")], [("agents", "state_value")]
    )  # MAPPO: a centralised critic over every vehicle's observation
    collector = Collector(
        env,
        actor,
        frames_per_batch=args.frames_per_batch,
        total_frames=args.frames,
        auto_register_policy_transforms=False,
    )
    collector.set_seed(args.seed)
    loss = ClipPPOLoss(
        actor, critic, clip_epsilon=0.2, entropy_coeff=0.01, normalize_advantage=False
    )
    loss.set_keys(
        reward=("agents", "reward"),
        action=("agents", "action"),
        sample_log_prob=("agents", "action_log_prob"),
        value=("agents", "state_value"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
    )
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    optim = torch.optim.Adam(loss.parameters(), lr=3e-3)
    start = time.time()
    for i, data in enumerate(collector):
        with torch.no_grad():  # GAE over each vehicle's team reward and done flags
            loss.value_estimator(
                data,
                params=loss.critic_network_params,
                target_params=loss.target_critic_network_params,
            )
        flat = data.reshape(-1)
        for _ in range(4):
            for idx in torch.randperm(len(flat)).split(250):
                out = loss(flat[idx])
                total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optim.step()
        collector.update_policy_weights_()
        reward = float(data["next", "agents", "reward"].mean())
        print(f"rollout {i + 1}: mean team reward {reward:.3f}", flush=True)
    collector.shutdown()

    def greedy(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        x = torch.as_tensor(np.stack([obs[a] for a in agents], 1))  # [B, N, W]
        with torch.no_grad():
            logits = actor.module[0](x)  # the actor's network: its most likely action
        return {a: logits[:, i].argmax(-1).numpy() for i, a in enumerate(agents)}

    result = fleet.score(greedy)
    result.update(frames=args.frames, seed=args.seed, seconds=round(time.time() - start, 1))
    print(f"exact ratio {result['ratio']:.4f} of the centralised optimum ({json.dumps(result)})")
    if args.out:
        table = fleet.policy_table(greedy).tolist()
        with open(args.out, "w") as f:
            json.dump({**result, "overrides": args.overrides, "table": table}, f)


if __name__ == "__main__":
    main()
