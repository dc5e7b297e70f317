"""The paper's claims (MODEL.md § The paper's claims) checked against measured numbers.

Every check is a plain function of numbers, so the verdict logic is tested on synthetic data; the
thresholds that turn the paper's words into tests ("far above", "rises", "about") are named here and
printed with the verdicts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

HOLDS, FAILS, UNTESTED = "holds", "does not hold", "not tested"

SAME_REWARD_TOL = 0.05
"""Claim 1: "converge to the same total reward" = a DQN profile and the Q-learning profile of the same
kind (ours with ours, paper with paper) end within 5 % of the optimum of each other."""
FAR_ABOVE = 0.5
"""Claim 1: "far above round-robin" = the learner closes at least half the gap from round-robin to
the optimum."""
TREND_RHO = 0.8
"""Claim 2: "rises" / "falls" = Spearman's rank correlation with p^v_1 at least 0.8 in that direction
(and the last value beyond the first)."""
BEAT_MARGIN = 0.01
"""Claim 2: "beat round-robin" = better by more than 1 % of round-robin's value at every p^v_1."""
MISS_RANGE = (0.15, 0.30)
"""Claim 2: the learned policies' miss detection "within 0.15 – 0.3"."""


@dataclass
class Verdict:
    """One row of the claims table."""

    claim: str
    subject: str
    measured: str
    verdict: str

    def as_dict(self) -> dict[str, str]:
        """Plain dict (a CSV row)."""
        return {
            "claim": self.claim,
            "subject": self.subject,
            "measured": self.measured,
            "verdict": self.verdict,
        }


@dataclass
class FigureNumbers:
    """What the claims are checked against (all exact values of greedy or fixed policies).

    Attributes:
        optimum_episode: the optimum's total reward per episode in panel (a).
        round_robin_episode: round-robin's, same definition.
        final_episode: learner → its final greedy policies' total reward per episode (mean over seeds).
        episodes_to_95: learner → first training episode at which the mean greedy curve reaches
            95 % of the optimum (None: never within the run).
        p1_speed: the p^v_1 values of panels (b)–(d), increasing.
        sweep: subject (learners, ``optimal``, ``round_robin``) → metric → mean value at each p^v_1.
        r4_miss: r4 → miss detection of the optimal policy (claim 3); empty to skip.
        r4_throughput: r4 → throughput of the optimal policy (context for claim 3).
    """

    optimum_episode: float
    round_robin_episode: float
    final_episode: dict[str, float]
    episodes_to_95: dict[str, float | None]
    p1_speed: list[float]
    sweep: dict[str, dict[str, list[float]]]
    r4_miss: dict[float, float] = field(default_factory=dict)
    r4_throughput: dict[float, float] = field(default_factory=dict)


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation (average ranks for ties; NaN if either side is constant)."""

    def ranks(v: Sequence[float]) -> list[float]:
        order = sorted(range(len(v)), key=lambda i: v[i])
        r = [0.0] * len(v)
        i = 0
        while i < len(order):
            j = i
            while j + 1 < len(order) and v[order[j + 1]] == v[order[i]]:
                j += 1
            for k in range(i, j + 1):
                r[order[k]] = (i + j) / 2 + 1
            i = j + 1
        return r

    if len(x) != len(y) or len(x) < 2:
        return math.nan
    rx, ry = ranks(x), ranks(y)
    mx, my = sum(rx) / len(rx), sum(ry) / len(ry)
    sxy = sum((a - mx) * (b - my) for a, b in zip(rx, ry, strict=True))
    sxx = sum((a - mx) ** 2 for a in rx)
    syy = sum((b - my) ** 2 for b in ry)
    if sxx == 0 or syy == 0:
        return math.nan
    return sxy / math.sqrt(sxx * syy)


def trend(p: Sequence[float], values: Sequence[float], direction: int) -> tuple[bool, str]:
    """Whether ``values`` rise (direction +1) or fall (−1) with ``p``, and the numbers that say so."""
    rho = spearman(p, values)
    ok = (
        not math.isnan(rho)
        and direction * rho >= TREND_RHO
        and direction * (values[-1] - values[0]) > 0
    )
    shown = "constant" if math.isnan(rho) else f"ρ = {rho:+.2f}"
    return ok, f"{values[0]:.4g} → {values[-1]:.4g} ({shown})"


def beats(values: Sequence[float], baseline: Sequence[float], direction: int) -> tuple[bool, str]:
    """Whether ``values`` beat ``baseline`` at every point: higher (direction +1) or lower (−1) by
    more than ``BEAT_MARGIN`` of the baseline's magnitude (a tie is not a win)."""
    gaps = [direction * (a - b) for a, b in zip(values, baseline, strict=True)]
    ok = all(g > BEAT_MARGIN * abs(b) for g, b in zip(gaps, baseline, strict=True))
    rel = [g / abs(b) if b else math.inf for g, b in zip(gaps, baseline, strict=True)]
    word = "higher" if direction > 0 else "lower"
    return ok, (
        f"{word} than round-robin by {min(gaps):+.3g} … {max(gaps):+.3g} "
        f"({min(rel):+.1%} … {max(rel):+.1%}; > {BEAT_MARGIN:.0%} asked)"
    )


def _v(ok: bool) -> str:
    return HOLDS if ok else FAILS


def _is_dqn(name: str) -> bool:
    return name.startswith("dqn")


def _is_qlearning(name: str) -> bool:
    return name.startswith("qlearning")


def claim1(
    optimum_episode: float,
    round_robin_episode: float,
    final_episode: Mapping[str, float],
    episodes_to_95: Mapping[str, float | None],
) -> list[Verdict]:
    """Claim 1 (panel (a)) from ``FigureNumbers``' first four fields: the verdicts of 1a–1c."""
    out: list[Verdict] = []
    opt, rr = optimum_episode, round_robin_episode
    learners = list(final_episode)
    dqns = [k for k in learners if _is_dqn(k)]
    qls = [k for k in learners if _is_qlearning(k)]

    # Claim 1 — panel (a).
    c1a = "1a. DQN and Q-learning converge to the same total reward (Fig. 2a)"
    pairs = [(d, q) for d in dqns for q in qls if d.endswith("_paper") == q.endswith("_paper")]
    for d, q in pairs:
        gap = abs(final_episode[d] - final_episode[q])
        out.append(
            Verdict(
                c1a,
                f"{d} vs {q}",
                f"{final_episode[d]:.1f} vs {final_episode[q]:.1f} (optimum {opt:.1f}): "
                f"{gap / abs(opt):.1%} of the optimum apart (≤ {SAME_REWARD_TOL:.0%} asked)",
                _v(gap <= SAME_REWARD_TOL * abs(opt)),
            )
        )
    if not pairs:
        out.append(Verdict(c1a, "-", "needs a DQN and a Q-learning profile", UNTESTED))
    c1b = "1b. … far above round-robin"
    for k in learners:
        closed = (final_episode[k] - rr) / (opt - rr) if opt != rr else math.nan
        out.append(
            Verdict(
                c1b,
                k,
                f"{final_episode[k]:.1f} vs round-robin {rr:.1f}: {closed:.0%} of the gap to "
                f"the optimum closed (≥ {FAR_ABOVE:.0%} asked)",
                _v(closed >= FAR_ABOVE),
            )
        )
    c1c = "1c. DQN needs fewer episodes than Q-learning (paper: ~170 vs ~280) to approach it"
    for d, q in pairs:
        ed, eq = episodes_to_95.get(d), episodes_to_95.get(q)
        measured = f"episodes to 95 % of the optimum: {d} {_ep(ed)}, {q} {_ep(eq)}"
        if ed is None:
            verdict = FAILS
        elif eq is None:
            verdict = HOLDS
        else:
            verdict = _v(ed < eq)
        out.append(Verdict(c1c, f"{d} vs {q}", measured, verdict))
    if not pairs:
        out.append(Verdict(c1c, "-", "needs a DQN and a Q-learning profile", UNTESTED))
    return out


def check_claims(n: FigureNumbers) -> list[Verdict]:
    """The claims table: one verdict per (claim, subject)."""
    out = claim1(n.optimum_episode, n.round_robin_episode, n.final_episode, n.episodes_to_95)
    out += _claim2(n)

    # Claim 3 — r4.
    c3 = "3. raising r4 (e.g. to 50 or 100) lowers miss detection"
    if len(n.r4_miss) >= 2:
        r4s = sorted(n.r4_miss)
        base = r4s[0]
        higher = r4s[1:]
        ok = all(n.r4_miss[r] < n.r4_miss[base] for r in higher)
        measured = ", ".join(
            f"r4={r:g}: miss {n.r4_miss[r]:.3f}"
            + (f" (throughput {n.r4_throughput[r]:.3f})" if r in n.r4_throughput else "")
            for r in r4s
        )
        out.append(Verdict(c3, "optimal", measured, _v(ok)))
    else:
        out.append(Verdict(c3, "optimal", "needs ≥ 2 r4 values", UNTESTED))
    return out


def _ep(x: float | None) -> str:
    return "not within the run" if x is None else f"{x:g}"


def format_claims(verdicts: Sequence[Verdict]) -> str:
    """The claims table as Markdown."""
    lines = ["| claim | subject | measured | verdict |", "|---|---|---|---|"]
    for v in verdicts:
        cells = [v.claim, v.subject, v.measured, f"**{v.verdict}**"]
        lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
    return "\n".join(lines)


def summarize(verdicts: Sequence[Verdict]) -> Mapping[str, int]:
    """Counts of each verdict."""
    out = {HOLDS: 0, FAILS: 0, UNTESTED: 0}
    for v in verdicts:
        out[v.verdict] += 1
    return out


def _claim2(n: FigureNumbers) -> list[Verdict]:
    """Claim 2 — panels (b)–(d)."""
    out: list[Verdict] = []
    p = n.p1_speed
    subjects = [k for k in n.sweep if k != "round_robin"]
    rr_sweep = n.sweep.get("round_robin", {})
    c2a = "2a. learned policies' average reward rises with p^v_1 (Fig. 2b)"
    c2b = "2b. round-robin's average reward falls with p^v_1 (Fig. 2b)"
    c2c = "2c. learned policies beat round-robin on throughput (Fig. 2c)"
    c2d = "2d. learned policies beat round-robin on miss detection (Fig. 2d)"
    c2e = "2e. learned policies' miss detection falls with p^v_1 (Fig. 2d)"
    c2f = f"2f. … within {MISS_RANGE[0]} – {MISS_RANGE[1]} (Fig. 2d)"
    if len(p) < 2 or not rr_sweep:
        out.append(Verdict("2. (Fig. 2b–d)", "-", "needs ≥ 2 p^v_1 values", UNTESTED))
    else:
        for k in subjects:
            ok, msg = trend(p, n.sweep[k]["avg_reward"], +1)
            out.append(Verdict(c2a, k, msg, _v(ok)))
        ok, msg = trend(p, rr_sweep["avg_reward"], -1)
        out.append(Verdict(c2b, "round_robin", msg, _v(ok)))
        for k in subjects:
            for metric, label in (
                ("throughput", "packets sent"),
                ("link_capacity", "link capacity used"),
            ):
                ok, msg = beats(n.sweep[k][metric], rr_sweep[metric], +1)
                out.append(Verdict(c2c, f"{k} ({label})", msg, _v(ok)))
        for k in subjects:
            ok, msg = beats(n.sweep[k]["miss_detection"], rr_sweep["miss_detection"], -1)
            out.append(Verdict(c2d, k, msg, _v(ok)))
        for k in subjects:
            ok, msg = trend(p, n.sweep[k]["miss_detection"], -1)
            out.append(Verdict(c2e, k, msg, _v(ok)))
        for k in subjects:
            miss = n.sweep[k]["miss_detection"]
            lo, hi = min(miss), max(miss)
            out.append(
                Verdict(
                    c2f,
                    k,
                    f"{lo:.3f} … {hi:.3f}",
                    _v(MISS_RANGE[0] <= lo and hi <= MISS_RANGE[1]),
                )
            )
    return out
