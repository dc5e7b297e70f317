"""Benchmark: env steps per second of DFRCEnv for several batch sizes (medians of repeated runs).

python recipes/bench_env.py                          # table + bench_env.csv in the run dir
python recipes/bench_env.py sizes=[1024,65536] threads=[1] repeats=3
"""

from __future__ import annotations

import csv
import statistics
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params
from irdrc.experiments.config import CONF_DIR, register_scenarios

MODES = ("dynamics", "step", "rollout")

register_scenarios()


def _runner(mode: str, params: Params, n: int, iters: int, device: str, seed: int):
    """A callable doing ``iters`` batched steps of ``mode`` (built once, outside the timing)."""
    gen = torch.Generator(device=device)
    gen.manual_seed(seed)
    env = DFRCEnv(params, batch_size=[n], device=device, seed=seed)
    if mode == "dynamics":
        dyn = env.dynamics
        state = dyn.reset_states(n, gen)

        def run() -> None:
            nonlocal state
            for _ in range(iters):
                action = torch.randint(0, 2, (n,), generator=gen, device=device)
                state = dyn.step(state, action, gen).state

    elif mode == "step":
        td = env.reset()

        def run() -> None:
            nonlocal td
            for _ in range(iters):
                td["action"] = torch.randint(0, 2, (n,), generator=gen, device=device)
                _, td = env.step_and_maybe_reset(td)

    else:

        def run() -> None:
            env.rollout(iters, break_when_any_done=False)

    return run


@hydra.main(config_path=str(CONF_DIR), config_name="bench_env", version_base=None)
def main(cfg: DictConfig) -> None:
    """Print the throughput table and write it as CSV."""
    params = Params.from_config(cfg)
    bad = [m for m in cfg.modes if m not in MODES]
    if bad:
        raise ValueError(f"modes: unknown {bad}; choose from {list(MODES)}")
    if cfg.repeats < 1 or any(n < 1 for n in cfg.sizes) or any(t < 1 for t in cfg.threads):
        raise ValueError("repeats, sizes and threads must be >= 1")
    rows = []
    print(f"{'N':>7} {'threads':>7} {'mode':>9} {'median M steps/s':>17} {'min':>7} {'max':>7}")
    for threads in cfg.threads:
        torch.set_num_threads(int(threads))
        for n in cfg.sizes:
            iters = int(min(cfg.max_iters, max(cfg.min_iters, cfg.target_env_steps // n)))
            for mode in cfg.modes:
                run = _runner(mode, params, int(n), iters, cfg.device, cfg.seed)
                run()  # warm-up (allocator, lazy init)
                rates = []
                for _ in range(cfg.repeats):
                    t0 = time.perf_counter()
                    run()
                    rates.append(n * iters / (time.perf_counter() - t0))
                med = statistics.median(rates)
                row = {
                    "num_envs": n,
                    "threads": threads,
                    "mode": mode,
                    "iters": iters,
                    "repeats": cfg.repeats,
                    "median_steps_per_s": med,
                    "min_steps_per_s": min(rates),
                    "max_steps_per_s": max(rates),
                }
                rows.append(row)
                print(
                    f"{n:>7} {threads:>7} {mode:>9} {med / 1e6:>17.3f} "
                    f"{min(rates) / 1e6:>7.3f} {max(rates) / 1e6:>7.3f}",
                    flush=True,
                )
    best = max(rows, key=lambda r: r["median_steps_per_s"] if r["mode"] != "dynamics" else 0)
    print(
        f"\nbest env throughput: {best['median_steps_per_s'] / 1e6:.2f} M steps/s "
        f"(N={best['num_envs']}, threads={best['threads']}, mode={best['mode']})"
    )
    out = Path(HydraConfig.get().runtime.output_dir) / cfg.csv
    with out.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
