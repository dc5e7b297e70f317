"""Benchmarks behind ``recipes/bench_dqn.py``: env steps and seconds to 95 % / 99 % of the optimum."""

from __future__ import annotations

import math
import statistics
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from irdrc.agents import dqn
from irdrc.agents.base import Hooks, RunRecord
from irdrc.core.env import DFRCEnv
from irdrc.core.model import ExactModel, build_model
from irdrc.core.params import Params, to_plain
from irdrc.core.solve import ExactScorer, stationary_occupancy
from irdrc.experiments.config import compose
from irdrc.experiments.grid import candidate_overrides, parse_grid
from irdrc.experiments.results import (
    md_table,
    policy_differences,
    read_policy_csv,
    state_label,
    write_rows_csv,
    write_table_md,
)
from irdrc.experiments.results import read_csv_rows as read_csv

SUMMARY_KEYS = (
    "env_steps_per_second",
    "updates_per_second",
    "env_steps_to_95",
    "seconds_to_95",
    "env_steps_to_99",
    "seconds_to_99",
    "later_evals_at_99",
    "final_ratio",
)


def profile_config(overrides: list[str]) -> dqn.DQNConfig:
    """The DQN config (algo and network) ``recipes/dqn.py`` composes from ``overrides``."""
    return dqn.DQNConfig.from_node(compose("dqn", list(overrides)))


def _fmt(values: list) -> str:
    hit = [v for v in values if v is not None]
    if len(hit) < len(values):
        return f"{len(hit)}/{len(values)} reached" + (
            f" (range {min(hit):.4g}–{max(hit):.4g})" if hit else ""
        )
    return f"median {statistics.median(hit):.4g} (range {min(hit):.4g}–{max(hit):.4g})"


def comm_states(scorer: ExactScorer) -> list[dict[str, Any]]:
    """The states where the optimum communicates, each with its label, its share of time under the
    optimum, its true action gap Q*(s, comm) − Q*(s, radar), and the optimality ratio of the
    optimum with radar in that state alone (what one wrong greedy action there costs)."""
    model, opt = scorer.model, scorer.optimal
    visits = stationary_occupancy(model, opt.policy).sum(0)
    out = []
    for s in (opt.policy == 0).nonzero().flatten().tolist():
        flipped = opt.policy.clone()
        flipped[s] = 1
        out.append(
            {
                "state": s,
                "label": state_label(s, model.params.env.levels),
                "visit_frequency": float(visits[s]),
                "true_gap": float(opt.q[0, s] - opt.q[1, s]),
                "ratio_if_radar_here": scorer.ratio(flipped),
            }
        )
    return out


def value_slope(values: torch.Tensor, queue: torch.Tensor) -> float:
    """Least-squares slope of ``values`` [S] against the queue length ``queue`` [S] (value per
    packet queued). The paper's reward does not depend on the queue, so the optimum's is 0; a
    shift of every value (reward centering) leaves it unchanged."""
    d = queue.double() - queue.double().mean()
    v = values.double() - values.double().mean()
    return float((d * v).sum() / (d * d).sum())


def samples_to_resolve(
    model: ExactModel,
    q: torch.Tensor,
    values: torch.Tensor,
    states: list[int],
    gamma: float,
    *,
    draws: int = 20_000,
    z: float = 2.326,
    seed: int = 0,
) -> list[dict[str, float]]:
    """How much data telling the better action apart takes at each of ``states``: the true gap
    Q*(s, comm) − Q*(s, radar) (``q`` [2, S], ``values`` V* [S]), the standard deviation σ_a of the
    one-step target r + γ·V*(s′) under each action (``draws`` simulated steps each), and
    n = (z·√(σ_comm² + σ_radar²) / |gap|)², the samples *of each action* after which the difference
    of two sample means has the gap's sign with probability Φ(z) (z = 2.326: 99 %). A learner that
    pools states sharing the same value (e.g. every queue length, where the reward ignores the
    queue) needs n divided by at most the number it pools. Diagnostic only: it scores, it steers
    nothing."""
    from irdrc.core.env import Dynamics

    if not states:
        return []
    dyn = Dynamics(model.params)
    gen = torch.Generator().manual_seed(int(seed))
    idx = torch.tensor(states, dtype=torch.int64).repeat_interleave(draws)
    sigma = []
    for a in (0, 1):
        out = dyn.step(idx, torch.full_like(idx, a), gen)
        target = out.reward.double() + gamma * values.double()[out.state]
        sigma.append(target.view(len(states), draws).std(1))
    rows = []
    for i, st in enumerate(states):
        gap = float(q[0, st] - q[1, st])
        spread = math.hypot(float(sigma[0][i]), float(sigma[1][i]))
        rows.append(
            {
                "state": st,
                "true_gap": gap,
                "sigma_comm": float(sigma[0][i]),
                "sigma_radar": float(sigma[1][i]),
                "samples_per_action": (z * spread / abs(gap)) ** 2 if gap != 0 else math.inf,
            }
        )
    return rows


def _gap_tracer(
    states: list[dict[str, Any]],
    profile: str,
    seed: int,
    rows: list[dict[str, Any]],
    scorer: ExactScorer | None = None,
):
    """An ``on_values`` hook appending the learned gap at ``states`` to ``rows``, and with
    ``scorer`` the learned and the true mean and slope in the queue length of V = max_a Q (with
    reward centering the learned mean is V's shifted by −r̄/(1 − γ); the slope is not)."""
    true_slope = learned_slope = true_mean = learned_mean = math.nan
    if scorer is not None:
        true_slope = value_slope(scorer.optimal.values, scorer.model.queue)
        true_mean = float(scorer.optimal.values.mean())

    def on_values(env_steps: int, q: torch.Tensor) -> None:
        nonlocal learned_slope, learned_mean
        if scorer is not None:
            v = q[0].max(-1).values
            learned_slope = value_slope(v, scorer.model.queue)
            learned_mean = float(v.double().mean())
        for st in states:
            gap = float(q[0, st["state"], 0] - q[0, st["state"], 1])
            rows.append(
                {
                    "profile": profile,
                    "seed": seed,
                    "env_steps": env_steps,
                    "state": st["label"],
                    "visit_frequency": st["visit_frequency"],
                    "ratio_if_radar_here": st["ratio_if_radar_here"],
                    "true_gap": st["true_gap"],
                    "learned_gap": gap,
                    "learned_value_slope": learned_slope,
                    "true_value_slope": true_slope,
                    "learned_value_mean": learned_mean,
                    "true_value_mean": true_mean,
                }
            )

    return on_values


def run_bench_dqn(cfg: DictConfig, out: Path) -> int:
    """Train every (profile, seed), profiles alternated seed by seed in one process; per run: the
    training speed (env steps/s, updates/s, the share of collecting, storing and learning) and the
    env steps and seconds to 95 % / 99 %; then the cost of one update for K learners stacked in
    one network (``cfg.stacked``) against K single ones. Writes ``bench_dqn.csv`` and
    ``bench_dqn.md``; with ``trace_gaps`` also the learned action gaps (``gap_trace.csv``)."""
    start = time.perf_counter()
    torch.set_num_threads(int(cfg.num_threads))
    params = Params.from_config(cfg)
    scorer = ExactScorer(build_model(params), gamma=float(cfg.optimum_gamma))
    trace = bool(cfg.get("trace_gaps", False))
    states = comm_states(scorer) if trace else []
    gap_rows: list[dict[str, Any]] = []
    rows: list[dict[str, Any]] = []
    profiles = candidate_overrides({"candidates": cfg.profiles})
    extra = [str(o) for o in cfg.get("overrides", [])]
    configs = {name: profile_config([*ov, *extra]) for name, ov in profiles.items()}
    for seed in cfg.seeds:
        for name, config in configs.items():
            hooks = Hooks(
                on_values=_gap_tracer(states, name, int(seed), gap_rows, scorer) if trace else None
            )
            rec = dqn.train(
                params,
                config,
                seed=int(seed),
                device=cfg.device,
                eval_every_frames=int(cfg.eval.every_frames),
                scorers=scorer,
                hooks=hooks,
            )
            rows.append(_speed_row(name, int(seed), rec))
            row = rows[-1]
            print(
                f"{name:>14} seed {seed}: {row['env_steps_per_second']:,.0f} env steps/s, "
                f"{row['updates_per_second']:.0f} updates/s of training; 99 % at "
                f"{row['env_steps_to_99']} steps / {row['seconds_to_99']} s; final "
                f"{row['final_ratio']:.4f}",
                flush=True,
            )
            if trace:
                _print_gaps(states, gap_rows)
    stacked = [int(k) for k in cfg.get("stacked", [])]
    stack_rows = stacked_update_cost(configs[next(iter(configs))], stacked) if stacked else []
    write_rows_csv(Path(out) / cfg.csv, rows)
    table = speed_table(rows, list(configs)) + (
        "\n\n" + stacked_table(stack_rows) if stack_rows else ""
    )
    print("\n" + table)
    write_table_md(Path(out) / "bench_dqn.md", table, time.perf_counter() - start)
    print(f"\nwrote {Path(out) / cfg.csv} and {Path(out) / 'bench_dqn.md'}")
    if trace:
        write_rows_csv(Path(out) / "gap_trace.csv", gap_rows)
        print(f"wrote {Path(out) / 'gap_trace.csv'}")
    return 0


def _speed_row(name: str, seed: int, rec: RunRecord) -> dict[str, Any]:
    """One run of the speed benchmark: its counts, its phases' seconds, and how soon it learned."""
    info = rec.info
    train = info["seconds_collect"] + info["seconds_store"] + info["seconds_learn"]
    t99 = rec.first_reaching(0.99)
    later = [e for e in rec.history if t99 is not None and e["env_steps"] > t99]
    return {
        "profile": name,
        "seed": seed,
        "env_steps": rec.env_steps,
        "updates": rec.updates,
        "training_seconds": round(train, 3),
        "evaluation_seconds": round(info.get("seconds_evaluate", 0.0), 3),
        **{
            f"share_{k}": round(info[f"seconds_{k}"] / train, 3)
            for k in ("collect", "store", "learn")
        },
        "env_steps_per_second": rec.env_steps / train,
        "updates_per_second": rec.updates / info["seconds_learn"] if info["seconds_learn"] else 0.0,
        "env_steps_to_95": rec.first_reaching(0.95),
        "seconds_to_95": rec.first_reaching(0.95, at="wall_seconds"),
        "env_steps_to_99": t99,
        "seconds_to_99": rec.first_reaching(0.99, at="wall_seconds"),
        "later_evals_at_99": (
            sum(e["optimality_ratio"] >= 0.99 for e in later) / len(later) if later else None
        ),
        "final_ratio": rec.history[-1]["optimality_ratio"],
    }


def _print_gaps(states: list[dict[str, Any]], gap_rows: list[dict[str, Any]]) -> None:
    final = gap_rows[-len(states) :]
    if final:
        print(
            f"    final learned slope of V in the queue length: "
            f"{final[-1]['learned_value_slope']:+.3f} per packet (true "
            f"{final[-1]['true_value_slope']:+.3f}); mean of V "
            f"{final[-1]['learned_value_mean']:.1f} (true {final[-1]['true_value_mean']:.1f})"
        )
        print(
            "    final learned gap: "
            + "; ".join(
                f"{st['label']}: {g['learned_gap']:+.2f} (true {st['true_gap']:+.2f})"
                for st, g in zip(states, final, strict=True)
            )
        )


def speed_table(rows: list[dict[str, Any]], profiles: list[str]) -> str:
    """The speed benchmark as Markdown: per profile, medians over its seeds, and its training speed
    as a ratio to the first profile's (measured in the same run, alternately)."""
    body, base = [], None
    for name in profiles:
        mine = [r for r in rows if r["profile"] == name]
        if not mine:
            continue
        rate = statistics.median(r["env_steps_per_second"] for r in mine)
        base = base or rate
        t99 = [r for r in mine if r["env_steps_to_99"] is not None]
        body.append(
            [
                name,
                len(mine),
                f"{mine[0]['env_steps']:,}".replace(",", " "),
                f"{statistics.median(r['updates'] for r in mine):,.0f}".replace(",", " "),
                f"{statistics.median(r['training_seconds'] for r in mine):.2f}",
                f"{rate:,.0f}".replace(",", " "),
                f"{rate / base:.3g}",
                f"{statistics.median(r['updates_per_second'] for r in mine):.0f}",
                " / ".join(
                    f"{statistics.median(r[f'share_{k}'] for r in mine):.0%}"
                    for k in ("collect", "store", "learn")
                ),
                f"{len(t99)}/{len(mine)}",
                _fmt([r["env_steps_to_99"] for r in t99]) if t99 else "—",
                _fmt([r["seconds_to_99"] for r in t99]) if t99 else "—",
                _fmt([r["final_ratio"] for r in mine]),
            ]
        )
    return md_table(
        [
            "profile",
            "seeds",
            "env steps",
            "updates",
            "training s",
            "env steps/s of training",
            "× the first profile",
            "updates/s",
            "collect / store / learn",
            "reached 99 %",
            "env steps to 99 %",
            "s to 99 %",
            "final ratio",
        ],
        body,
    ) + (
        "\n\nMedians over the seeds (ranges in brackets); one thread; training seconds leave the "
        "exact evaluations out."
    )


def stacked_update_cost(
    config: dqn.DQNConfig, learners: list[int], repeats: int = 20
) -> list[dict]:
    """The cost of one gradient update per learner when K learners are one stacked network
    (TorchRL's ``MultiAgentMLP``, unshared parameters, vmapped; one ``DQNLoss`` on [B, K]
    samples) against K = 1, on ``config``'s network and batch: whether running seeds as learners
    of one process would beat running them one per process."""
    from tensordict import TensorDict
    from torchrl.modules import MultiAgentMLP, QValueActor
    from torchrl.objectives import DQNLoss, SoftUpdate

    from irdrc.agents.offpolicy import ACTIVATIONS, make_qnet

    env = DFRCEnv(Params(), batch_size=[1])
    spec, B, net = env.action_spec_unbatched, config.batch_size, config.network
    width = env.observation_spec["observation"].shape[-1]
    out = []
    for k in learners:
        if k == 1:
            qnet = make_qnet(env, net)
        else:
            norm = (
                {
                    "norm_class": torch.nn.LayerNorm,
                    "norm_kwargs": {"normalized_shape": net.hidden[0]},
                }
                if net.layer_norm
                else {}
            )
            body = MultiAgentMLP(
                n_agent_inputs=width,
                n_agent_outputs=2,
                n_agents=k,
                centralized=False,
                share_params=False,
                num_cells=list(net.hidden),
                activation_class=ACTIVATIONS[net.activation],
                **norm,
            )
            qnet = QValueActor(module=body, in_keys=["observation"], spec=spec)
        loss = DQNLoss(
            qnet, loss_function="l2", delay_value=True, double_dqn=True, action_space=spec
        )
        loss.make_value_estimator(gamma=config.gamma)
        opt = torch.optim.Adam(loss.parameters(), lr=config.lr, foreach=True)
        target = SoftUpdate(loss, tau=config.tau)
        shape = [B] if k == 1 else [B, k]
        flag = torch.zeros(*shape, 1, dtype=torch.bool)
        td = TensorDict(
            {
                "observation": torch.rand(*shape, width),
                "action": torch.randint(0, 2, shape),
                "next": {
                    "observation": torch.rand(*shape, width),
                    "reward": torch.randn(*shape, 1),
                    "done": flag,
                    "terminated": flag,
                },
            },
            shape,
        )

        times = []
        for i in range(repeats + 1):  # the first update warms up
            t0 = time.perf_counter()
            value = loss(td)["loss"]
            opt.zero_grad()
            value.backward()
            opt.step()
            target.step()
            if i:
                times.append(time.perf_counter() - t0)
        out.append({"learners": k, "ms_per_update": 1e3 * statistics.median(times)})
    return out


def stacked_table(rows: list[dict]) -> str:
    """The stacked-learners check as Markdown: ms per update in all and per learner."""
    single = next((r["ms_per_update"] for r in rows if r["learners"] == 1), None)
    return (
        md_table(
            [
                "learners in one stacked network",
                "ms per update",
                "ms per learner",
                "× one learner's speed",
            ],
            [
                [
                    r["learners"],
                    f"{r['ms_per_update']:.1f}",
                    f"{r['ms_per_update'] / r['learners']:.2f}",
                    f"{single / (r['ms_per_update'] / r['learners']):.2f}" if single else "—",
                ]
                for r in rows
            ],
        )
        + "\n\nMedian of 20 updates each, one thread, batch and network of the first profile."
    )


def run_bench_robust(cfg: DictConfig, out: Path, scenario: list[str] | None = None) -> int:
    """Every (candidate, scenario, seed) of ``cfg`` as one DQN run through the sweep engine; per
    run and per (candidate, scenario): the final ratio, env steps and seconds to the threshold,
    and the share of evaluations after first reaching it that stay there. Writes
    ``bench_robust.csv`` (a row per run) and ``bench_robust.md`` (the table, then every run that
    does not hold, with the states where it differs from the optimum)."""
    import json

    from irdrc.experiments.sweep import execute, plan

    start = time.perf_counter()
    th = float(cfg.threshold)
    grid = {
        "env.p1.speed": [float(p) for p in to_plain(cfg.p1_speed)],
        "reward.r4": [float(r) for r in to_plain(cfg.r4)],
        "seed": [int(s) for s in to_plain(cfg.seeds)],
    }
    base = [
        *(scenario or []),
        *[str(o) for o in cfg.overrides],
        "eval.mc_episodes=0",
        f"eval.every_frames={int(cfg.eval.every_frames)}",
        f"optimum_gamma={float(cfg.optimum_gamma)}",
        "checkpoint.every_frames=0",
    ]
    candidates = candidate_overrides(cfg)
    planned, owner = [], {}
    for name, extra in candidates.items():
        for p in plan("dqn", parse_grid(grid), [*base, *extra]):
            planned.append(p)
            owner[p["point_id"]] = name
    code = execute(cfg, planned, out)
    rows = []
    for p in planned:
        tdir = Path(out) / "trials" / p["point_id"]
        if not (tdir / "summary.json").is_file():
            continue
        hist = read_csv(tdir / "metrics.csv")
        summary = json.loads((tdir / "summary.json").read_text())
        ratios = [float(r["optimality_ratio"]) for r in hist]
        first = next((i for i, r in enumerate(ratios) if r >= th), None)
        later = ratios[first + 1 :] if first is not None else []
        final = float(summary["optimality_ratio"])  # the final policy's (selected, when on)
        rows.append(
            {
                "candidate": owner[p["point_id"]],
                **dict(p["point"].items()),
                "final_ratio": final,
                "holds": final >= th,
                "last_network_ratio": ratios[-1],
                "env_steps_to_threshold": int(hist[first]["env_steps"])
                if first is not None
                else None,
                "seconds_to_threshold": float(hist[first]["wall_seconds"])
                if first is not None
                else None,
                "later_evals_at_threshold": sum(r >= th for r in later) / len(later)
                if later
                else None,
                "later_evals": len(later),
                "later_evals_ok": sum(r >= th for r in later),
                "training_env_steps": int(summary.get("training_env_steps", summary["env_steps"])),
                "measurement_env_steps": int(summary.get("measurement_env_steps", 0)),
                "env_steps": int(summary["env_steps"]),
                "wall_seconds": float(summary["wall_seconds"]),
                "point_id": p["point_id"],
            }
        )
    write_rows_csv(Path(out) / cfg.csv, rows)
    keys = [k for k in grid if k != "seed"]
    scenarios = parse_grid({k: grid[k] for k in keys})
    table = robust_table(rows, candidates, scenarios, th, len(grid["seed"]))
    print("\n" + table)
    failures = []
    for row in rows:
        if row["holds"]:
            continue
        p = next(q for q in planned if q["point_id"] == row["point_id"])
        model = build_model(Params.from_config(OmegaConf.create(p["cfg"])))
        tdir = Path(out) / "trials" / p["point_id"]
        learned = read_policy_csv(tdir / "policy.csv", model.num_states)
        solution = ExactScorer(model, float(cfg.optimum_gamma)).optimal
        label = " ".join(f"{k}={v}" for k, v in p["point"].items())
        text = f"{row['candidate']} {label}: final {row['final_ratio']:.4f}; " + policy_differences(
            model, learned, solution.policy
        )
        differ = (learned != solution.policy).nonzero().flatten().tolist()
        need = samples_to_resolve(
            model, solution.q, solution.values, differ, float(cfg.optimum_gamma)
        )
        if need:
            gaps = [abs(r["true_gap"]) for r in need]
            ns = [r["samples_per_action"] for r in need]
            text += (
                f"\n  where it differs, |true gap| {min(gaps):.3g}–{max(gaps):.3g}; telling the "
                f"actions apart at 99 % takes {min(ns):.3g}–{max(ns):.3g} samples of each action "
                "per state (samples_to_resolve)"
            )
        failures.append(text)
        print("\n" + text)
    if failures:
        table += (
            "\n\nRuns that do not hold, and where their final policy differs:\n\n"
            + "\n\n".join("```\n" + f + "\n```" for f in failures)
        )
    write_table_md(Path(out) / "bench_robust.md", table, time.perf_counter() - start)
    print(f"\nwrote {Path(out) / cfg.csv} and {Path(out) / 'bench_robust.md'}")
    return code


def robust_table(
    rows: list[dict[str, Any]],
    candidates: dict[str, list[str]],
    scenarios: list[dict[str, Any]],
    th: float,
    seeds: int,
) -> str:
    """The benchmark as Markdown: one row per (candidate, scenario) and one per candidate over all
    its scenarios (medians over the runs; steps and seconds to the threshold over the runs that
    reached it; later evaluations pooled)."""

    def med(values: list) -> str:
        values = [v for v in values if v is not None]
        return f"{statistics.median(values):,.0f}".replace(",", " ") if values else "—"

    def summary(mine: list[dict[str, Any]]) -> list[str]:
        reached = [r for r in mine if r["env_steps_to_threshold"] is not None]
        ok = sum(r["later_evals_ok"] for r in mine)
        n = sum(r["later_evals"] for r in mine)
        secs = [r["seconds_to_threshold"] for r in reached]
        return [
            f"{sum(r['holds'] for r in mine)}/{len(mine)}",
            f"{min(r['final_ratio'] for r in mine):.4f}",
            f"{statistics.median(r['final_ratio'] for r in mine):.4f}",
            f"{len(reached)}/{len(mine)}",
            med([r["env_steps_to_threshold"] for r in reached]),
            f"{statistics.median(secs):.2f}" if secs else "—",
            f"{ok}/{n} ({ok / n:.3f})" if n else "—",
            med([r["training_env_steps"] for r in mine])
            + (
                " + " + med([r["measurement_env_steps"] for r in mine])
                if any(r["measurement_env_steps"] for r in mine)
                else ""
            ),
            f"{statistics.median(r['wall_seconds'] for r in mine):.1f}",
        ]

    body = []
    for name in candidates:
        theirs = [r for r in rows if r["candidate"] == name]
        if not theirs:
            continue
        for point in scenarios:
            mine = [r for r in theirs if all(r[k] == v for k, v in point.items())]
            if mine:
                label = ", ".join(f"{k} = {v:g}" for k, v in point.items())
                body.append([name, label, *summary(mine)])
        if len(scenarios) > 1:
            body.append([f"**{name}**", "**all**", *summary(theirs)])
    th_pct = f"{th:.0%}"
    return (
        md_table(
            [
                "candidate",
                "scenario",
                f"holds ≥ {th:g} at the end",
                "worst final",
                "median final",
                f"reached {th_pct}",
                f"median env steps to {th_pct}",
                f"median s to {th_pct}",
                f"later evaluations ≥ {th:g}",
                "env steps per run (training + measurement)",
                "median s per run",
            ],
            body,
        )
        + f"\n\n{seeds} seeds per scenario; each candidate's overrides: "
        + "; ".join(f"{n}: `{' '.join(o) or '(none)'}`" for n, o in candidates.items())
        + "."
    )


def run_bench_constrained(cfg: DictConfig, out: Path, scenario: list[str] | None = None) -> int:
    """Every (p^v_1, target, seed) of ``cfg`` as one ``recipes/constrained.py
    learner=dqn_lagrangian`` run through the sweep engine, scored exactly against the LP: per cell,
    the runs whose miss detection is ≤ target + ``miss_tolerance`` and those whose objective is
    ≥ ``objective_share`` of the LP optimum, with env steps (training + measurement) and seconds."""
    start = time.perf_counter()
    import json

    from irdrc.experiments.sweep import execute, plan

    tol, share = float(cfg.miss_tolerance), float(cfg.objective_share)
    grid = {
        "env.p1.speed": [float(p) for p in to_plain(cfg.p1_speed)],
        "target_miss": [float(t) for t in to_plain(cfg.targets)],
        "seed": [int(s) for s in to_plain(cfg.seeds)],
    }
    base = [
        *(scenario or []),
        "learner=dqn_lagrangian",
        *[str(o) for o in cfg.overrides],
        f"optimum_gamma={float(cfg.optimum_gamma)}",
    ]
    planned = plan("constrained", parse_grid(grid), base)
    code = execute(cfg, planned, out)
    rows = []
    for p in planned:
        path = Path(out) / "trials" / p["point_id"] / "summary.json"
        if not path.is_file():
            continue
        s = json.loads(path.read_text())
        learner = s["learner"]
        miss = float(s["metrics"]["miss_detection"])
        rows.append(
            {
                **dict(p["point"].items()),
                "objective": s["objective"],
                "lp_value": s["optimal_value"],
                "value": s["value"],
                "objective_ratio": s["objective_ratio"],
                "miss_detection": miss,
                "lp_miss_detection": s["optimal"]["miss_detection"],
                "miss_ok": miss <= float(p["point"]["target_miss"]) + tol,
                "objective_ok": float(s["objective_ratio"]) >= share,
                "mu": learner["mu"],
                "randomised_state": learner.get("switch_state"),
                "ranked": learner.get("ranked"),
                "path_promise": learner.get("path_promise"),
                "rank_promise": learner.get("rank_promise"),
                "training_env_steps": s["training_env_steps"],
                "measurement_env_steps": s["measurement_env_steps"],
                "env_steps": s["env_steps"],
                "wall_seconds": s["wall_seconds"],
            }
        )
    write_rows_csv(Path(out) / cfg.csv, rows)
    table = constrained_bench_table(rows, grid, tol, share)
    print(
        f"\nLagrangian DQN against the LP ({len(grid['seed'])} seeds per cell): miss detection ≤ "
        f"target + {tol:g}, objective ≥ {share:g} of the LP optimum"
    )
    print(table)
    write_table_md(Path(out) / "bench_constrained.md", table, time.perf_counter() - start)
    print(f"\nwrote {Path(out) / cfg.csv} and {Path(out) / 'bench_constrained.md'}")
    return code


def _steps(n: float) -> str:
    """Env steps in words a table reads at a glance: 80 000, 1.2 M, 279 M."""
    if n >= 1e6:
        return f"{n / 1e6:.3g} M"
    return f"{n:,.0f}".replace(",", " ")


def constrained_bench_table(
    rows: list[dict[str, Any]], grid: dict[str, list], tol: float, share: float
) -> str:
    """The benchmark's Markdown table: one line per (p^v_1, target) cell."""
    header = (
        f"| p^v_1 | target | runs | miss ≤ target + {tol:g} | objective ≥ {share:g} of the LP | "
        "worst miss | worst ratio | median ratio | median env steps (training + measurement) | "
        "median s |"
    )
    lines = [header, "|---" * (header.count("|") - 1) + "|"]
    for point in parse_grid({k: grid[k] for k in ("env.p1.speed", "target_miss")}):
        mine = [r for r in rows if all(r[k] == v for k, v in point.items())]
        if not mine:
            continue
        train = statistics.median(r["training_env_steps"] for r in mine)
        meas = statistics.median(r["measurement_env_steps"] for r in mine)
        total = statistics.median(r["env_steps"] for r in mine)
        lines.append(
            f"| {point['env.p1.speed']:g} | {point['target_miss']:g} | {len(mine)} | "
            f"{sum(r['miss_ok'] for r in mine)} | {sum(r['objective_ok'] for r in mine)} | "
            f"{max(r['miss_detection'] for r in mine):.4f} | "
            f"{min(r['objective_ratio'] for r in mine):.3f} | "
            f"{statistics.median(r['objective_ratio'] for r in mine):.3f} | "
            f"{_steps(train)} + {_steps(meas)} = {_steps(total)} | "
            f"{statistics.median(r['wall_seconds'] for r in mine):.0f} |"
        )
    return "\n".join(lines)
