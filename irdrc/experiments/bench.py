"""Benchmarks behind ``recipes/bench_dqn.py``: env steps and seconds to 95 % / 99 % of the optimum."""

from __future__ import annotations

import statistics
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from irdrc.agents import dqn
from irdrc.core.model import build_model
from irdrc.core.params import Params
from irdrc.core.solve import ExactScorer
from irdrc.experiments.config import compose
from irdrc.experiments.results import write_rows_csv

SUMMARY_KEYS = (
    "env_steps_to_95",
    "seconds_to_95",
    "env_steps_to_99",
    "seconds_to_99",
    "later_evals_at_99",
    "final_ratio",
    "updates_per_second",
)


def profile_config(name: str, overrides: list[str]) -> dqn.DQNConfig:
    """The DQN config (algo and network) of ``recipes/dqn.py algo=<name>``."""
    return dqn.DQNConfig.from_node(compose("dqn", [f"algo={name}", *overrides]))


def _fmt(values: list) -> str:
    hit = [v for v in values if v is not None]
    if len(hit) < len(values):
        return f"{len(hit)}/{len(values)} reached" + (
            f" (range {min(hit):.4g}–{max(hit):.4g})" if hit else ""
        )
    return f"median {statistics.median(hit):.4g} (range {min(hit):.4g}–{max(hit):.4g})"


def run_bench_dqn(cfg: DictConfig, out: Path) -> int:
    """Train every (profile, seed), print medians and ranges, write ``cfg.csv`` into ``out``."""
    torch.set_num_threads(int(cfg.num_threads))
    params = Params.from_config(cfg)
    scorer = ExactScorer(build_model(params), gamma=float(cfg.optimum_gamma))
    rows: list[dict[str, Any]] = []
    for name in cfg.profiles:
        extra = []
        if name in cfg.frames_override:
            extra.append(f"algo.total_frames={int(cfg.frames_override[name])}")
        config = profile_config(name, extra)
        for seed in cfg.seeds:
            rec = dqn.train(
                params,
                config,
                seed=int(seed),
                device=cfg.device,
                eval_every_frames=int(cfg.eval.every_frames),
                scorers=scorer,
            )
            t99 = rec.first_reaching(0.99)
            later = [e for e in rec.history if t99 is not None and e["env_steps"] > t99]
            row = {
                "profile": name,
                "seed": int(seed),
                "total_frames": rec.env_steps,
                "updates": rec.updates,
                "wall_seconds": round(rec.wall_seconds, 3),
                "env_steps_to_95": rec.first_reaching(0.95),
                "seconds_to_95": rec.first_reaching(0.95, at="wall_seconds"),
                "env_steps_to_99": t99,
                "seconds_to_99": rec.first_reaching(0.99, at="wall_seconds"),
                "later_evals_at_99": (
                    sum(e["optimality_ratio"] >= 0.99 for e in later) / len(later)
                    if later
                    else None
                ),
                "final_ratio": rec.history[-1]["optimality_ratio"],
                "updates_per_second": round(rec.updates / rec.wall_seconds, 1),
            }
            rows.append(row)
            print(
                f"{name:>10} seed {seed}: 95 % at {row['env_steps_to_95']} steps, 99 % at {t99} "
                f"steps / {row['seconds_to_99'] and round(row['seconds_to_99'], 2)} s; later evals "
                f"≥ 99 %: {row['later_evals_at_99']}; final {row['final_ratio']:.4f}; "
                f"{rec.env_steps} steps in {rec.wall_seconds:.1f} s",
                flush=True,
            )
    print()
    for name in cfg.profiles:
        rs = [r for r in rows if r["profile"] == name]
        print(f"{name} ({len(rs)} seeds, {rs[0]['total_frames']} env steps each):")
        for key in SUMMARY_KEYS:
            print(f"  {key:<18} {_fmt([r[key] for r in rs])}")
    write_rows_csv(Path(out) / cfg.csv, rows)
    print(f"\nwrote {Path(out) / cfg.csv}")
    return 0
