"""``recipes/bench_env.py``: the simulator's throughput — batched env steps per second for several
batch sizes, and single-env steps per second against a plain numpy baseline measured in the same
run (medians of repeated timed runs).

    python recipes/bench_env.py                      # BENCHMARKS.md's table
    python recipes/bench_env.py 'sizes=[1024]' 'threads=[1]'
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np
import torch

from irdrc.core.checks import INT, build, check_choice, check_list, check_numbers, grouped, numbers
from irdrc.core.dynamics import Dynamics
from irdrc.core.env import DFRCEnv
from irdrc.core.params import Params
from irdrc.runs.compose import Composed
from irdrc.runs.results import md_table, write_rows_csv, write_table_md
from irdrc.runs.sections import check_common, scenario_field

if TYPE_CHECKING:
    from irdrc.runs.scaffold import Run

NAME = "bench_env"

MODES = ("dynamics", "step", "rollout", "gym_vec")
"""Batched modes, measured at every N: bare ``Dynamics.step``; ``env.step_and_maybe_reset`` (what a
collector runs); ``env.rollout``; ``gymnasium.make_vec`` (its ``step``)."""
SINGLE_MODES = ("numpy_single", "gym")
"""Single-env modes, measured at N = 1, one thread: a plain numpy implementation of the same MDP
(the baseline), and ``gymnasium.make("irdrc/DFRC-v0")``."""


def _runner(
    mode: str, params: Params, n: int, iters: int, device: str, seed: int
) -> Callable[[], Any]:
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

    elif mode == "rollout":

        def run() -> None:
            env.rollout(iters, break_when_any_done=False)

    else:  # gym_vec
        venv = gymnasium.make_vec("irdrc/DFRC-v0", num_envs=n, params=params)
        venv.reset(seed=seed)
        rng = np.random.default_rng(seed)

        def run() -> None:
            for _ in range(iters):
                venv.step(rng.integers(0, 2, n))

    return run


def _single_runner(mode: str, params: Params, iters: int, seed: int) -> Callable[[], Any]:
    """A callable doing ``iters`` single-env steps of ``mode`` with random actions."""
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, 2, iters).tolist()
    if mode == "gym":
        env = gymnasium.make("irdrc/DFRC-v0", params=params)
        env.reset(seed=seed)

        def run() -> None:
            for a in actions:
                _, _, _, truncated, _ = env.step(a)
                if truncated:
                    env.reset()

        return run
    step, reset = numpy_single_env(params, seed)
    reset()

    def run_np() -> None:
        for a in actions:
            if step(a)[3]:
                reset()

    return run_np


def numpy_single_env(params: Params, seed: int) -> tuple[Callable[..., Any], Callable[..., Any]]:
    """The baseline: one env of the same MDP in plain numpy, from ``Dynamics``' tables (as a user
    would write it): ``(step(a) -> (obs, reward, terminated, truncated, info), reset())``."""
    dyn = Dynamics(params)
    event = dyn.event_prob.numpy()
    next1 = dyn.next1.numpy()
    reward = dyn.reward.numpy()
    capacity = dyn.capacity.numpy()
    cdf = dyn.arrival_cdf.numpy()
    weights = np.array([16, 8, 4, 2, 1])
    obs_table = dyn.obs.numpy()
    D, S, T = dyn.queue_capacity, dyn.num_states, params.env.horizon
    rng = np.random.default_rng(seed)
    state = {"s": 0, "t": 0}

    def reset() -> tuple[np.ndarray, dict[str, Any]]:
        state["s"], state["t"] = int(rng.integers(S)), 0
        return obs_table[state["s"]].copy(), {}

    def step(a: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        s = state["s"]
        f = s & 31
        u = rng.random(7)
        ev = bool(u[0] < event[f])
        arrivals = int(np.searchsorted(cdf, u[1], side="right"))
        f2 = int((weights * (u[2:] < next1[a * 32 + f])).sum())
        nu = int(capacity[a * 32 + f])
        total = (s >> 5) + arrivals
        sent = min(total, nu)
        d2 = min(total - sent, D)
        state["s"], state["t"] = d2 * 32 + f2, state["t"] + 1
        info = {"event": ev, "sent": sent, "dropped": total - sent - d2}
        r = float(reward[a * 64 + ev * 32 + f])
        return obs_table[state["s"]].copy(), r, False, state["t"] >= T, info

    return step, reset


def _time(run: Callable[[], Any], repeats: int) -> list[float]:
    """Seconds of ``repeats`` timed calls of ``run``, after one warm-up call."""
    run()  # warm-up (allocator, lazy init)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return times


def _row(
    n: int, threads: int, mode: str, iters: int, repeats: int, times: list[float]
) -> dict[str, Any]:
    rates = [n * iters / t for t in times]
    return {
        "num_envs": n,
        "threads": threads,
        "mode": mode,
        "iters": iters,
        "repeats": repeats,
        "median_steps_per_s": statistics.median(rates),
        "min_steps_per_s": min(rates),
        "max_steps_per_s": max(rates),
    }


@dataclass(frozen=True)
class Config:
    """The benchmark's keys (``irdrc/conf/bench_env.yaml``)."""

    params: Params = scenario_field()
    sizes: tuple[int, ...] = (1, 64, 1024, 16384, 65536)
    threads: tuple[int, ...] = (1, 2)
    modes: tuple[str, ...] = (*SINGLE_MODES, *MODES)
    single_steps: int = 100_000
    repeats: int = 5
    target_env_steps: int = 2_000_000
    min_iters: int = 20
    max_iters: int = 400
    device: str = "cpu"
    seed: int = 0
    csv: str = "bench_env.csv"

    def __post_init__(self) -> None:
        check_common(self)
        for key in ("sizes", "threads"):
            value = check_list(
                key, getattr(self, key), numbers(1, 10**8, integer=True), distinct=True
            )
            object.__setattr__(self, key, value)
        mode = lambda key, m: check_choice(key, m, MODES + SINGLE_MODES)  # noqa: E731
        object.__setattr__(self, "modes", check_list("modes", self.modes, mode, distinct=True))
        check_numbers(
            self,
            "",
            (
                ("single_steps", 1, 10**8, INT),
                ("repeats", 1, 1000, INT),
                ("target_env_steps", 1, 10**12, INT),
                ("min_iters", 1, 10**9, INT),
                ("max_iters", 1, 10**9, INT),
            ),
        )


def load(composed: Composed, resume: dict[str, Any] | None = None) -> Config:
    """The typed config, checked."""
    return build(Config, composed.cfg)


def run(cfg: Config, run: Run) -> int:
    """Print the throughput table (batched modes at every N and thread count; single-env modes
    with their ratio to the numpy baseline measured in the same run) and write it as CSV."""
    run_bench_env(cfg, run.dir)
    run.finish(None)
    return 0


def run_bench_env(cfg: Config, out: Any) -> None:
    """The benchmark (see ``run``) into ``out``."""
    start = time.perf_counter()
    params = cfg.params
    rows = []
    print(f"{'N':>7} {'threads':>7} {'mode':>12} {'median M steps/s':>17} {'min':>7} {'max':>7}")

    def show(row: dict[str, Any]) -> None:
        rows.append(row)
        med, lo, hi = (
            row[k] / 1e6 for k in ("median_steps_per_s", "min_steps_per_s", "max_steps_per_s")
        )
        print(
            f"{row['num_envs']:>7} {row['threads']:>7} {row['mode']:>12} {med:>17.3f} {lo:>7.3f} {hi:>7.3f}",
            flush=True,
        )

    single = [m for m in cfg.modes if m in SINGLE_MODES]
    if single:
        torch.set_num_threads(1)
        iters = int(cfg.single_steps)
        for mode in single:
            times = _time(_single_runner(mode, params, iters, int(cfg.seed)), int(cfg.repeats))
            show(_row(1, 1, mode, iters, int(cfg.repeats), times))
    for threads in cfg.threads:
        torch.set_num_threads(int(threads))
        for n in cfg.sizes:
            iters = int(min(cfg.max_iters, max(cfg.min_iters, cfg.target_env_steps // n)))
            for mode in [m for m in cfg.modes if m in MODES]:
                run = _runner(mode, params, int(n), iters, cfg.device, int(cfg.seed))
                show(
                    _row(
                        int(n),
                        int(threads),
                        mode,
                        iters,
                        int(cfg.repeats),
                        _time(run, int(cfg.repeats)),
                    )
                )
    base = {r["mode"]: r["median_steps_per_s"] for r in rows if r["mode"] in SINGLE_MODES}
    if "numpy_single" in base:
        print("\nsingle env, one thread (ratio to the numpy baseline of this run):")
        for mode, rate in base.items():
            print(f"  {mode:<13} {rate / 1e3:8.1f} k steps/s  ×{rate / base['numpy_single']:.2f}")
    batched = [r for r in rows if r["mode"] in ("step", "rollout", "gym_vec")]
    if batched:
        best = max(batched, key=lambda r: r["median_steps_per_s"])
        print(
            f"\nbest batched env throughput: {best['median_steps_per_s'] / 1e6:.2f} M steps/s "
            f"(N={best['num_envs']}, threads={best['threads']}, mode={best['mode']})"
        )
    write_rows_csv(out / cfg.csv, rows)
    write_table_md(out / "bench_env.md", bench_env_table(rows), time.perf_counter() - start)


def bench_env_table(rows: list[dict[str, Any]]) -> str:
    """The benchmark as Markdown: batched modes in M steps/s (median over repeats) with N and
    threads as rows, then each single-env mode in k steps/s with its ratio to the numpy baseline
    of the same run."""
    parts = []
    batched = [r for r in rows if r["mode"] in MODES]
    if batched:
        modes = [m for m in MODES if any(r["mode"] == m for r in batched)]
        keys = sorted({(r["threads"], r["num_envs"]) for r in batched})
        rate = {(r["threads"], r["num_envs"], r["mode"]): r["median_steps_per_s"] for r in batched}
        parts.append(
            md_table(
                ["N envs", "threads", *(f"{m} (M steps/s)" for m in modes)],
                [
                    [grouped(n), t]
                    + [f"{rate[(t, n, m)] / 1e6:.3g}" if (t, n, m) in rate else "" for m in modes]
                    for t, n in keys
                ],
            )
        )
    single = {r["mode"]: r["median_steps_per_s"] for r in rows if r["mode"] in SINGLE_MODES}
    if single:
        base = single.get("numpy_single")
        parts.append(
            md_table(
                ["single env, one thread", "k steps/s", "ratio to numpy_single (this run)"],
                [
                    [m, f"{v / 1e3:.1f}", f"{v / base:.2f}" if base else "n/a"]
                    for m, v in single.items()
                ],
            )
        )
    return "\n\n".join(parts)
