"""A policy as a table: ``policy.csv`` (one row per state) and its readable forms — the policy by
factor configuration and queue length, and where it differs from the optimum."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from irdrc.core.checks import grouped
from irdrc.core.states import decode_state
from irdrc.runs.results import atomic_write_text, read_csv_rows, read_csv_table

if TYPE_CHECKING:
    from irdrc.core.params import Params

POLICY_COLUMNS = ("d", "c", "r", "w", "v", "m", "action", "p_radar")
"""``policy.csv``: one row per state in index order: the state's factors, ``action`` (the mode
chosen: 0 = communication, 1 = radar; the likelier one for a randomised policy) and ``p_radar``
(the probability of radar: 0 or 1 for a deterministic policy)."""


def state_label(s: int, levels: Sequence[int] | None = None) -> str:
    """``d=3 c=0 r=1 w=0 v=2 m=0`` (and ``phase=1`` with bursty arrivals) for state index ``s``;
    ``levels`` as in ``Params.env.factor_levels`` (None: v1)."""
    cols = decode_state(torch.tensor(int(s)), levels).tolist()
    names = ("d", "c", "r", "w", "v", "m", "phase")
    return " ".join(f"{n}={int(x)}" for n, x in zip(names, cols, strict=False))


def write_policy_csv(
    path: Path,
    policy: torch.Tensor,
    levels: Sequence[int] | None = None,
    shares: Sequence[float] | None = None,
) -> None:
    """``policy.csv`` (see ``POLICY_COLUMNS``; a ``phase`` column after ``m`` with bursty arrivals)
    from an [S] action table or [S, 2] probabilities; ``levels`` as in ``Params.env.factor_levels``
    (None: v1). With ``shares`` (MODEL.md § D) the columns after the state are ``action`` and its
    radar share ``rho`` (``env.actions=levels``), or ``rho`` alone when ``policy`` is [S] float
    shares and ``shares`` is ``()`` (``continuous``)."""
    policy = torch.as_tensor(policy).cpu()
    if shares is not None:
        cols = decode_state(torch.arange(policy.shape[0]), levels)
        header = list(POLICY_COLUMNS[:6]) + (["phase"] if cols.shape[-1] == 7 else [])
        if len(shares):
            rho = torch.as_tensor(shares, dtype=torch.float64)[policy.long()]
            header += ["action", "rho"]
            rows = [
                [*c, int(a), repr(float(r))]
                for c, a, r in zip(cols.tolist(), policy.tolist(), rho.tolist(), strict=True)
            ]
        else:
            header += ["rho"]
            rows = [
                [*c, repr(float(r))] for c, r in zip(cols.tolist(), policy.tolist(), strict=True)
            ]
        text = "\n".join([",".join(header), *(",".join(map(str, r)) for r in rows)])
        atomic_write_text(Path(path), text + "\n")
        return
    if policy.ndim == 2:
        p_radar = policy[:, 1].double()
        actions = (p_radar > 0.5).long()
    else:
        actions = policy.long()
        p_radar = actions.double()
    cols = decode_state(torch.arange(actions.numel()), levels)
    header = list(POLICY_COLUMNS)
    if cols.shape[-1] == 7:
        header.insert(6, "phase")
    lines = [",".join(header)]
    lines += [
        ",".join(map(str, [*c, int(a), _prob(float(p))]))
        for c, a, p in zip(cols.tolist(), actions.tolist(), p_radar.tolist(), strict=True)
    ]
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


SHARE_POLICY_COLUMNS = ("rho", "rho_alt", "p_alt")
"""A randomised ρ policy's columns after the state (``irdrc.core.share_cmdp.SharePolicy``): the
share used, and the other share used there with probability ``p_alt`` (0 where deterministic); with
``env.actions=levels`` the shares' levels (``action``, ``action_alt``) too."""


def write_share_policy_csv(
    path: Path,
    policy: Any,
    levels: Sequence[int] | None = None,
    shares: Sequence[float] | None = None,
) -> None:
    """``policy.csv`` of a ``SharePolicy`` (``SHARE_POLICY_COLUMNS``); ``shares``: the levels'
    shares, which adds each share's level index (``env.actions=levels``)."""
    cols = decode_state(torch.arange(policy.rho.shape[0]), levels)
    header = list(POLICY_COLUMNS[:6]) + (["phase"] if cols.shape[-1] == 7 else [])
    grid = None if shares is None else torch.as_tensor(shares, dtype=torch.float64)
    if grid is not None:

        def level(rho: torch.Tensor) -> list[int]:
            return (rho[:, None] - grid[None]).abs().argmin(-1).tolist()

        header += ["action", "rho", "action_alt", "rho_alt", "p_alt"]
        fields = [level(policy.rho), policy.rho.tolist(), level(policy.rho_alt)]
        fields += [policy.rho_alt.tolist(), policy.p_alt.tolist()]
    else:
        header += list(SHARE_POLICY_COLUMNS)
        fields = [policy.rho.tolist(), policy.rho_alt.tolist(), policy.p_alt.tolist()]
    rows = [
        ",".join(map(str, [*c, *(repr(f) if isinstance(f, float) else f for f in vals)]))
        for c, *vals in zip(cols.tolist(), *fields, strict=True)
    ]
    atomic_write_text(Path(path), "\n".join([",".join(header), *rows]) + "\n")


def _prob(p: float) -> str:
    return "0" if p == 0 else "1" if p == 1 else repr(p)


FITS = (
    " (a table fits the state space it was written for: the same env.queue_capacity, factor "
    "levels and traffic phases)"
)
"""What a table of another number of states is told."""


def read_share_csv(path: Path, num_states: int) -> torch.Tensor:
    """The [S] radar shares of a deterministic ρ policy's ``policy.csv`` (``recipes/sac.py``,
    ``ppo.py``: a ``rho`` column).

    Raises:
        ValueError: naming the file: unreadable, another number of rows, a share outside [0, 1],
            or a randomised ρ policy (``p_alt`` > 0: scored by ``recipes/constrained.py``).
    """
    rows = read_csv_rows(path)
    if len(rows) != num_states:
        raise ValueError(
            f"{path}: {len(rows)} rows, the scenario has S = {num_states} states{FITS}"
        )
    if any(float(r.get("p_alt") or 0) > 0 for r in rows):
        raise ValueError(
            f"{path}: a randomised ρ policy (p_alt > 0); recipes/constrained.py scores its own"
        )
    try:
        rho = torch.tensor([float(r["rho"]) for r in rows], dtype=torch.float64)
    except (KeyError, ValueError, TypeError) as err:
        raise ValueError(f"{path}: its rho column is not numbers ({err})") from None
    if bool(((rho < 0) | (rho > 1)).any()):
        raise ValueError(f"{path}: a radar share outside [0, 1]")
    return rho


def read_policy_csv(
    path: Path, num_states: int | None = None, probabilities: bool = False
) -> torch.Tensor:
    """Inverse of ``write_policy_csv``: the [S] action table, or with ``probabilities`` the [S, 2]
    probabilities of (comm, radar) from ``p_radar`` (files without that column: 0 or 1 from
    ``action``).

    Raises:
        ValueError: naming the file, if it is not a policy table (of ``num_states`` rows).
    """
    header, rows = read_csv_table(path)
    if "rho" in header:
        raise ValueError(
            f"{path}: a time-sharing policy (a radar share rho per state, MODEL.md § D): "
            "read_share_csv reads it"
        )
    if "action" not in header:
        raise ValueError(
            f"{path}: not a policy table: it needs a row per state with the columns "
            f"{','.join(POLICY_COLUMNS)} (a single-vehicle run's policy.csv); its columns are "
            f"{','.join(header) or 'none'}"
        )
    try:
        actions = torch.tensor([int(r["action"]) for r in rows], dtype=torch.int64)
        p_radar = torch.tensor(
            [float(r.get("p_radar") or r["action"]) for r in rows], dtype=torch.float64
        )
    except (KeyError, ValueError, TypeError) as err:
        raise ValueError(f"{path}: not a readable policy table ({type(err).__name__})") from err
    if actions.numel() == 0 or bool(((actions != 0) & (actions != 1)).any()):
        raise ValueError(f"{path}: a policy table holds one action 0 or 1 per state")
    if bool(((p_radar < 0) | (p_radar > 1) | p_radar.isnan()).any()):
        raise ValueError(f"{path}: p_radar must be a probability in every row")
    if num_states is not None and actions.numel() != num_states:
        raise ValueError(f"{path}: {actions.numel()} states, expected {num_states}{FITS}")
    if probabilities:
        return torch.stack([1 - p_radar, p_radar], -1)
    return actions


def policy_table(model: Any, actions: torch.Tensor) -> str:
    """Readable policy: one line per factor combination, its event probability and mode by queue.

    The mode column is ``comm``/``radar`` when the action is the same at every queue length,
    otherwise a string with one letter per d = 0 … D (C = comm, R = radar), or for D ≥ 64 its runs
    (``C×5 R×3120``). ``model`` is any single-vehicle exact model.
    """
    D = model.params.env.queue_capacity
    labels = _config_labels(model.params)
    acts = torch.as_tensor(actions).long().view(D + 1, len(labels))
    phase = " phase" if model.params.env.factor_levels[-1] > 1 else ""
    lines = [f"c r w v m{phase}  b  P(event)  mode (by d = 0 … D when it varies)"]
    for f, (bits, b) in enumerate(labels):
        mode = binary_mode(acts[:, f])
        pe = float(model.event[f])
        lines.append(f"{bits}  {b}  {pe:8.4f}  {mode}")
    return "\n".join(lines)


def _config_labels(params: Params) -> list[tuple[str, int]]:
    """Per factor configuration f: its levels as ``c r w v m[ phase]`` and b (MODEL.md § B.1)."""
    levels = params.env.factor_levels
    cols = decode_state(torch.arange(math.prod(levels)), levels)[:, 1:].tolist()
    return [(" ".join(map(str, c)), sum(c[1:5])) for c in cols]


def binary_mode(col: torch.Tensor) -> str:
    """One factor combination's modes over d = 0 … D: ``comm`` or ``radar`` when the same at every
    queue length, else a letter per d (C = comm, R = radar), or for D ≥ 64 its runs (``C×5
    R×3120``: comm for d = 0 … 4, radar above)."""
    if bool((col == col[0]).all()):
        return "radar" if int(col[0]) else "comm"
    if len(col) <= 64:
        return "".join("R" if int(a) else "C" for a in col)
    change = (col[1:] != col[:-1]).nonzero().flatten().tolist()
    ends = [*(i + 1 for i in change), len(col)]
    starts = [0, *ends[:-1]]
    return " ".join(
        f"{'R' if int(col[a]) else 'C'}×{b - a}" for a, b in zip(starts, ends, strict=True)
    )


def policy_differences(
    model: Any,
    actions: torch.Tensor,
    optimal: torch.Tensor,
    against: str = "the optimum",
    column: str = "optimum",
) -> str:
    """In words, where a policy differs from the optimum (or from the policy ``optimal`` another
    reference names: ``against`` in the sentence, ``column`` over its modes): one line per factor
    combination (c, r, w, v, m) with a difference, each policy's mode by queue length (C = comm,
    R = radar, d = 0 … D)."""
    D = model.params.env.queue_capacity
    labels = _config_labels(model.params)
    acts = torch.as_tensor(actions).long().view(D + 1, len(labels))
    opt = torch.as_tensor(optimal).long().view(D + 1, len(labels))
    levels = model.params.env.levels if model.params.env.actions == "levels" else 0
    n_diff = int((acts != opt).sum())
    if n_diff == 0:
        return f"the learned policy equals {against} in all {model.num_states} states"
    lines = [
        f"the learned policy differs from {against} in {n_diff} of {model.num_states} states "
        + (
            f"(radar share level by queue length d = 0 … D; level g is ρ = g/{levels - 1}):"
            if levels
            else "(mode by queue length d = 0 … D; C = comm, R = radar):"
        ),
        f"  c r w v m{' phase' if model.params.env.factor_levels[-1] > 1 else ''}  P(event)  learned       {column}",
    ]
    for f, (bits, _) in enumerate(labels):
        if bool((acts[:, f] == opt[:, f]).all()):
            continue

        def mode(col: torch.Tensor) -> str:
            if levels:  # § D's levels: the level, a digit per queue length (G ≤ 10), else "·"
                return "".join(str(int(a)) if levels <= 10 else "·" for a in col)
            return binary_mode(col)

        lines.append(
            f"  {bits}  {float(model.event[f]):8.4f}  {mode(acts[:, f]):<12}  {mode(opt[:, f])}"
        )
    return "\n".join(lines)


def share_table(model: Any, rho: torch.Tensor) -> str:
    """Readable ρ policy (MODEL.md § D): one line per factor combination, its event probability and
    its radar share — one value when the same at every queue length, else the range over d."""
    D = model.params.env.queue_capacity
    labels = _config_labels(model.params)
    shares = torch.as_tensor(rho, dtype=torch.float64).view(D + 1, len(labels))
    phase = " phase" if model.params.env.factor_levels[-1] > 1 else ""
    lines = [f"c r w v m{phase}  b  P(event)  radar share ρ (over d = 0 … D when it varies)"]
    for f, (bits, b) in enumerate(labels):
        col = shares[:, f]
        lo, hi = float(col.min()), float(col.max())
        text = f"{lo:.3f}" if hi - lo < 5e-4 else f"{lo:.3f} … {hi:.3f}"
        lines.append(f"{bits}  {b}  {float(model.event[f]):8.4f}  {text}")
    return "\n".join(lines)


def closest_decisions(model: Any, sol: Any, gamma: float, count: int = 6) -> str:
    """The optimum's closest calls, where a learner that estimates each mode's value from samples
    needs the most of them to choose right: the ``count`` factor combinations with the smallest
    margin |Q*(comm) − Q*(radar)| at some queue length, each with its mode, its margins over d, its
    share of the optimum's time, and — exactly, by policy evaluation — the optimum's ratio were the
    other mode taken there at every queue length. Then, at the queue length of its smallest
    margin: the spread of one step's value r + γ·V*(s′) under each mode (``one_step_spread``), the
    samples that tell the modes apart at 95 % — (1.96·(σ_comm + σ_radar)/margin)², split between
    the modes as their spreads — and the episodes in which the optimum visits the combination that
    often. ``sol`` is value iteration's ``Solution`` at ``gamma``. The ratio is n/a where the
    optimum earns ≤ 0 per step (a ratio to it would not rank policies)."""
    from irdrc.core.exact import one_step_spread, stationary_metrics, stationary_occupancy

    D = model.params.env.queue_capacity
    labels = _config_labels(model.params)
    nf = len(labels)
    margin = (sol.q[0] - sol.q[1]).abs().double().view(D + 1, nf)
    acts = torch.as_tensor(sol.policy).long().view(D + 1, nf)
    share = stationary_occupancy(model, sol.policy).sum(0).double().view(D + 1, nf).sum(0)
    best = stationary_metrics(model, sol.policy).avg_reward
    spread = one_step_spread(model, sol.values, gamma).view(2, D + 1, nf)
    per_episode = model.params.env.horizon * share
    phase = " phase" if model.params.env.factor_levels[-1] > 1 else ""
    lines = [
        f"c r w v m{phase}  P(event)  mode          margin (min … max over d)  share of time  "
        "other mode here: ratio  spread comm, radar  samples (95 %)  episodes"
    ]
    for f in torch.argsort(margin.min(0).values)[:count].tolist():
        mode = binary_mode(acts[:, f])
        flipped = acts.clone()
        flipped[:, f] = 1 - flipped[:, f]
        other = stationary_metrics(model, flipped.reshape(-1)).avg_reward
        ratio = f"{other / best:22.4f}" if best > 0 else f"{'n/a':>22}"
        lo, hi = float(margin[:, f].min()), float(margin[:, f].max())
        d = int(margin[:, f].argmin())
        sc, sr = float(spread[0, d, f]), float(spread[1, d, f])
        need = (1.96 * (sc + sr) / lo) ** 2 if lo > 0 else math.inf
        episodes = need / float(per_episode[f]) if per_episode[f] > 0 else math.inf
        lines.append(
            f"{labels[f][0]}  {float(model.event[f]):8.4f}  {mode:<12}  "
            f"{f'{lo:.4f} … {hi:.4f}':<25}  {float(share[f]):13.4f}  {ratio}  "
            f"{f'{sc:.2f}, {sr:.2f}':>18}  {_count(need):>14}  {_count(episodes):>8}"
        )
    return "\n".join(lines)


def _count(x: float) -> str:
    """A count for a table: ``12``, ``1 461``, ``inf``."""
    return "inf" if not math.isfinite(x) else grouped(x)
