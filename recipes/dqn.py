"""DQN from TorchRL parts, evaluated exactly against the optimum — the main job.

python recipes/dqn.py                                   # our profile, paper scenario
python recipes/dqn.py reward.r4=50 network=large env=ref_impl
python recipes/dqn.py algo=dqn_paper                    # the reference profile (1 M steps)
python recipes/dqn.py logger=wandb logger.mode=offline
python recipes/dqn.py resume=outputs/…/checkpoint.pt algo.total_frames=40000
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from irdrc import DFRCEnv, Params
from irdrc import qlearning as ql
from irdrc.config import CONF_DIR, register_scenarios, scenario_name
from irdrc.dqn import (
    DQNConfig,
    NetworkConfig,
    checkpoint_state,
    greedy_table,
    load_checkpoint,
    train,
)
from irdrc.evaluate import evaluate
from irdrc.metrics import Metrics, format_table
from irdrc.model import build_model
from irdrc.policies import table_policy
from irdrc.results import (
    atomic_write_text,
    summary_dict,
    write_policy_csv,
    write_rows_csv,
    write_summary,
)
from irdrc.solve import ExactScorer, stationary_metrics
from irdrc.tracking import log_scalars, make_logger

register_scenarios()


def qlearning_paper_metrics(params: Params, seed: int, cache_dir: Path, progress: bool) -> Metrics:
    """Exact metrics of Q-learning's paper profile trained on ``params`` (cached on disk)."""
    key = hashlib.sha256(json.dumps([params.to_dict(), seed, str(ql.PAPER)]).encode()).hexdigest()[
        :16
    ]
    path = cache_dir / f"qlearning_paper-{key}.json"
    if path.is_file():
        return Metrics.from_dict(json.loads(path.read_text()))
    bar = tqdm(
        total=ql.PAPER.episodes, unit="ep", desc="Q-learning paper profile", disable=not progress
    )
    res = ql.train(params, ql.PAPER, 1, seed, on_eval=lambda e: bar.update(e["episode"] - bar.n))
    bar.close()
    m = stationary_metrics(build_model(params), res.greedy[0])
    atomic_write_text(path, json.dumps(m.as_dict()))
    return m


@hydra.main(config_path=str(CONF_DIR), config_name="dqn", version_base=None)
def main(cfg: DictConfig) -> None:
    """Train, evaluate, write the run directory, print the comparison table."""
    torch.set_num_threads(int(cfg.num_threads))
    params = Params.from_config(cfg)
    algo = DQNConfig.from_dict(cfg.algo)
    net = NetworkConfig.from_dict(cfg.network)
    if cfg.eval.every_frames < 1 or cfg.eval.mc_episodes < 0 or cfg.eval.mc_num_envs < 1:
        raise ValueError(
            "eval.every_frames and eval.mc_num_envs must be >= 1, eval.mc_episodes >= 0"
        )
    out = Path(HydraConfig.get().runtime.output_dir)
    state = None
    if cfg.resume:
        state = load_checkpoint(Path(str(cfg.resume)).expanduser())
    scenario = scenario_name(cfg)
    exp_name = f"{scenario}__{algo.name}__{cfg.seed}"
    OmegaConf.save(cfg, out / "config.yaml")
    logger = make_logger(
        cfg.logger.backend,
        exp_name,
        out / "logs",
        project=cfg.logger.project,
        mode=cfg.logger.mode,
        config=OmegaConf.to_container(cfg, resolve=True),
    )
    # The optimum every result is read against is defined by the model's discount, whatever the
    # learner's own algo.gamma.
    scorer = ExactScorer(build_model(params), gamma=float(cfg.optimum_gamma))
    bar = tqdm(total=algo.total_frames, unit="step", disable=not cfg.progress, dynamic_ncols=True)
    latest = {"ratio": math.nan}

    def on_batch(info: dict) -> None:
        bar.update(info["env_steps"] - bar.n)
        bar.set_postfix(
            eps=f"{info['epsilon']:.3f}", loss=f"{info['loss']:.3g}", opt=f"{latest['ratio']:.4f}"
        )
        log_scalars(
            logger,
            {
                "train/epsilon": info["epsilon"],
                "train/loss": info["loss"],
                "train/beta": info["beta"],
            },
            info["env_steps"],
        )

    def on_eval(entry: dict) -> None:
        latest["ratio"] = entry["optimality_ratio"]
        log_scalars(
            logger,
            {
                f"eval/{k}": v
                for k, v in entry.items()
                if k not in ("env_steps", "wall_seconds", "updates")
            },
            entry["env_steps"],
        )
        log_scalars(
            logger,
            {"time/wall_seconds": entry["wall_seconds"], "time/updates": entry["updates"]},
            entry["env_steps"],
        )

    run = train(
        params,
        algo,
        net,
        seed=int(cfg.seed),
        device=cfg.device,
        eval_every_frames=int(cfg.eval.every_frames),
        on_eval=on_eval,
        on_batch=on_batch,
        state=state,
        scorer=scorer,
    )
    bar.close()
    print(
        f"replay sampler: {run.sampler_name}"
        + (" (prioritised)" if algo.prioritized else " (uniform)")
    )

    config_plain = OmegaConf.to_container(cfg, resolve=True)
    torch.save(checkpoint_state(run, config_plain), out / "checkpoint.pt")
    write_rows_csv(out / "metrics.csv", run.history)

    env = DFRCEnv(params, batch_size=[int(cfg.eval.mc_num_envs)], seed=int(cfg.seed) + 1)
    table = greedy_table(run.qnet, env)
    learned = scorer.metrics(table)
    model = scorer.model
    rows: dict[str, Metrics] = {f"{algo.name} (exact)": learned}
    errs = {}
    if cfg.eval.mc_episodes:
        ev = evaluate(table_policy(table), env, episodes=int(cfg.eval.mc_episodes))
        (
            rows[f"{algo.name} (Monte-Carlo, episodic)"],
            errs[f"{algo.name} (Monte-Carlo, episodic)"],
        ) = ev.metrics, ev.ci95
    rows["optimal (exact)"] = scorer.optimal_metrics
    rows["round_robin (exact)"] = stationary_metrics(model, "round_robin")
    if cfg.compare.qlearning_paper:
        cache = Path(str(cfg.cache_dir)).expanduser()
        rows["qlearning_paper (exact)"] = qlearning_paper_metrics(
            params, int(cfg.seed), cache, cfg.progress
        )

    ratios = [e["optimality_ratio"] for e in run.history]
    first99 = next((e["env_steps"] for e in run.history if e["optimality_ratio"] >= 0.99), None)
    write_summary(
        out / "summary.json",
        summary_dict(
            method=algo.name,
            scenario=scenario,
            seed=int(cfg.seed),
            env_steps=run.frames,
            wall_seconds=run.wall_seconds,
            metrics=learned,
            optimal=scorer.optimal_metrics,
            updates=run.updates,
            env_steps_to_99=first99,
            replay_sampler=run.sampler_name,
        ),
    )
    write_policy_csv(out / "policy.csv", table)
    log_scalars(logger, {"final/optimality_ratio": ratios[-1]}, run.frames)
    if logger is not None and hasattr(logger, "experiment") and cfg.logger.backend == "wandb":
        logger.experiment.finish()

    print(f"\nscenario={scenario} algo={algo.name} network={list(net.hidden)} seed={cfg.seed}")
    print(
        f"{run.frames} env steps, {run.updates} updates in {run.wall_seconds:.1f} s; "
        f"first ≥ 99 % of optimum at {first99} env steps (exact evaluation every "
        f"{cfg.eval.every_frames})\n"
    )
    print(format_table(rows, errors=errs))
    print(f"\nwrote summary.json, policy.csv, metrics.csv, config.yaml, checkpoint.pt to {out}")


if __name__ == "__main__":
    main()
