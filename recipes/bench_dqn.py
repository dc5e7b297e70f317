"""Benchmark: how fast each DQN profile reaches 95 % / 99 % of the exact optimum, over seeds.

    python recipes/bench_dqn.py                                # both profiles, 5 seeds
    python recipes/bench_dqn.py profiles=[dqn] seeds=[0,1,2]

Each profile is composed exactly as ``recipes/dqn.py algo=<profile>`` composes it, then trained with
the same ``irdrc.dqn.train``. Seconds are wall time of training (exact evaluations included).
"""

from __future__ import annotations

import statistics
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc import Params
from irdrc.config import CONF_DIR, compose, register_scenarios
from irdrc.dqn import DQNConfig, NetworkConfig, train
from irdrc.model import build_model
from irdrc.results import write_rows_csv
from irdrc.solve import ExactScorer

register_scenarios()


def profile_config(name: str, overrides: list[str]) -> tuple[DQNConfig, NetworkConfig]:
    """The algo and network configs of ``recipes/dqn.py algo=<name>``."""
    cfg = compose("dqn", [f"algo={name}", *overrides])
    return DQNConfig.from_dict(cfg.algo), NetworkConfig.from_dict(cfg.network)


def first(history: list[dict], key: str, threshold: float) -> float | None:
    """``key`` of the first evaluation whose optimality ratio reaches ``threshold``."""
    return next((e[key] for e in history if e["optimality_ratio"] >= threshold), None)


def _fmt(values: list) -> str:
    hit = [v for v in values if v is not None]
    if len(hit) < len(values):
        return f"{len(hit)}/{len(values)} reached" + (
            f" (range {min(hit):.4g}–{max(hit):.4g})" if hit else ""
        )
    return f"median {statistics.median(hit):.4g} (range {min(hit):.4g}–{max(hit):.4g})"


@hydra.main(config_path=str(CONF_DIR), config_name="bench_dqn", version_base=None)
def main(cfg: DictConfig) -> None:
    """Run every (profile, seed), print medians and ranges, write the CSV."""
    torch.set_num_threads(int(cfg.num_threads))
    params = Params.from_config(cfg)
    scorer = ExactScorer(build_model(params), gamma=float(cfg.optimum_gamma))
    out = Path(HydraConfig.get().runtime.output_dir)
    rows = []
    for name in cfg.profiles:
        extra = []
        if name in cfg.frames_override:
            extra.append(f"algo.total_frames={int(cfg.frames_override[name])}")
        algo, net = profile_config(name, extra)
        for seed in cfg.seeds:
            run = train(
                params,
                algo,
                net,
                seed=int(seed),
                device=cfg.device,
                eval_every_frames=int(cfg.eval_every_frames),
                scorer=scorer,
            )
            h = run.history
            t99 = first(h, "env_steps", 0.99)
            later = [e for e in h if t99 is not None and e["env_steps"] > t99]
            row = {
                "profile": name,
                "seed": int(seed),
                "total_frames": run.frames,
                "updates": run.updates,
                "wall_seconds": round(run.wall_seconds, 3),
                "env_steps_to_95": first(h, "env_steps", 0.95),
                "seconds_to_95": first(h, "wall_seconds", 0.95),
                "env_steps_to_99": t99,
                "seconds_to_99": first(h, "wall_seconds", 0.99),
                "later_evals_at_99": (
                    sum(e["optimality_ratio"] >= 0.99 for e in later) / len(later)
                    if later
                    else None
                ),
                "final_ratio": h[-1]["optimality_ratio"],
                "updates_per_second": round(run.updates / run.wall_seconds, 1),
            }
            rows.append(row)
            print(
                f"{name:>10} seed {seed}: 95 % at {row['env_steps_to_95']} steps, 99 % at {t99} steps / "
                f"{row['seconds_to_99'] and round(row['seconds_to_99'], 2)} s; later evals ≥ 99 %: "
                f"{row['later_evals_at_99']}; final {row['final_ratio']:.4f}; "
                f"{run.frames} steps in {run.wall_seconds:.1f} s",
                flush=True,
            )
    print()
    for name in cfg.profiles:
        rs = [r for r in rows if r["profile"] == name]
        print(f"{name} ({len(rs)} seeds, {rs[0]['total_frames']} env steps each):")
        for key in (
            "env_steps_to_95",
            "seconds_to_95",
            "env_steps_to_99",
            "seconds_to_99",
            "later_evals_at_99",
            "final_ratio",
            "updates_per_second",
        ):
            print(f"  {key:<18} {_fmt([r[key] for r in rs])}")
    write_rows_csv(out / cfg.csv, rows)
    print(f"\nwrote {out / cfg.csv}")


if __name__ == "__main__":
    main()
