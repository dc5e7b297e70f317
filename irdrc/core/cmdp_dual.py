"""The constrained problem of one constraint solved on its Lagrangian dual (MODEL.md § A), a little
work at a time: the LP's optimum (``irdrc.core.cmdp.solve_lp``), on the model's chains held as dense
or sparse matrices (docs/CONSTRAINED.md says it in words).

For λ ≥ 0, average-reward policy iteration finds the policies that maximise the long-run average
of J − λ·c (J the objective, c the constraint less its bound). The LP's optimum is the minimum over
λ of that maximum, piecewise linear in λ, a piece per policy (T − λ·C, T its objective and C its
constraint per step). The planner finds the best policy at λ = 0 (done if it keeps the constraint),
then one that keeps it (none: ``InfeasibleTarget``), and walks λ to λ*, where the best breaking and
best keeping policies cross; then it walks between the two through policies that attain λ*'s
optimality equation (``_walk_step``) until switching one state breaks the constraint. Those two
policies' occupation measures mixed so that it binds are the LP's optimum: the policy randomises in
one state and takes radar (the last action) where its chain never goes, as the LP's does.

Its unit of work is one policy evaluation (``advance``): an LU factorisation of the S × S chain,
dense or sparse (SuperLU; ``irdrc.core.chains.chain`` chooses). Policy iteration
assumes every policy's chain has one recurrent class (the model's Poisson arrivals reach a full
queue from every state); a singular system, or a policy iteration that comes back to a policy it
has left, stops it with ``SolverFailed``.
"""

from __future__ import annotations

import hashlib
import warnings
from typing import Any

import numpy as np
import torch

from irdrc.core.chains import chain
from irdrc.core.checks import grouped
from irdrc.core.cmdp import (
    CMDPSolution,
    Constraint,
    InfeasibleTarget,
    LPResult,
    SolverFailed,
    build_constraints,
    objective_table,
)
from irdrc.core.exact import ExactMDP

TIE_TOL = 1e-9
"""Policy improvement keeps a state's action unless another's value beats it by more than this
(relative to the largest value), so that ties cannot make it cycle."""

KEEP_TOL = 1e-12
"""A policy keeps the constraint when its C is at most this."""

DUST = 1e-12
"""A state of more stationary probability than this is in its policy's recurrent class; one of
less may be transient (``DualPlanner._recurrent``)."""

Line = tuple[np.ndarray, float, float, np.ndarray]
"""A policy found on the way, with its objective T and constraint C per step (the bound taken off),
and its stationary distribution."""

MAX_EVALUATIONS = 10_000
"""Policy evaluations one plan may take before ``SolverFailed`` (tens are usual)."""

_BLAS: Any = None


def one_blas_thread() -> Any:
    """A context in which NumPy's and SciPy's BLAS run on one thread: split over threads, an LU of a
    few hundred rows is at its slowest several times longer (a vehicle waits for its slowest)."""
    global _BLAS
    from threadpoolctl import ThreadpoolController

    if _BLAS is None:
        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


class DualPlanner:
    """The LP's optimum of ``objective`` subject to ``constraint``, one policy evaluation at a time
    (see the module docstring).

    Args:
        P: the transitions: [A, S, S] (``irdrc.core.chains.dense_transitions``), or A SciPy sparse S × S matrices
            (``irdrc.core.cmdp.transitions``).
        objective: [A, S] the per-step objective J (``irdrc.core.cmdp.objective_table``).
        constraint: the one constraint Σ x·coef ≤ bound (``build_constraints``'s first).

    The first policy iteration starts from radar (the last action) everywhere.
    """

    def __init__(
        self, P: np.ndarray | list[Any], objective: torch.Tensor, constraint: Constraint
    ) -> None:
        # dense: P itself; sparse: every action's rows stacked, [A·S, S] (the list is not kept)
        self.P: np.ndarray | None = None
        self.rows: Any = None
        if isinstance(P, np.ndarray):
            A, S = P.shape[0], P.shape[-1]
            self.P = P
        else:
            from scipy import sparse

            A, S = len(P), P[0].shape[-1]
            self.rows = sparse.vstack([sparse.csr_matrix(p) for p in P], format="csr")
        self.J = objective.to(torch.float64).cpu().numpy().reshape(A, S)
        self.c = constraint.coef.to(torch.float64).cpu().numpy().reshape(A, S)
        self.bound = float(constraint.bound)
        self.policy = np.full(S, A - 1)
        # 0: the best at λ = 0; 1: one that keeps the constraint; 2: towards λ*; 3: the walk at λ*
        self.stage, self.lam = 0, 0.0
        self.lo: Line | None = None  # the best breaking policy found
        self.hi: Line | None = None  # the best keeping one
        # the walk: its last keeping policy (None: its first step), where it goes (the breaking
        # end), the states it switches next, and how many the policy being evaluated switched
        self.walk: Line | None = None
        self.toward: np.ndarray | None = None
        self.stride = self.switched = 1
        self.evaluations = 0
        self.seen: set[str] = set()  # the policies this policy iteration has left

    def _reward(self) -> np.ndarray:
        if self.stage == 0:
            return self.J
        if self.stage == 1:
            return -self.c
        return self.J - self.lam * self.c

    def _evaluate(self, r: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """Gain, bias (0 at state 0) and stationary distribution of the current policy for r:
        (I − P_π)h + g·1 = r_π with h(0) = 0, the gain standing in h(0)'s column, and μ from the
        same factors (μ·M = e_0)."""
        import scipy.linalg as sl

        S = len(self.policy)
        idx = np.arange(S)
        e0 = np.zeros(S)
        e0[0] = 1.0
        try:
            with np.errstate(all="raise"), warnings.catch_warnings():
                warnings.simplefilter("error", sl.LinAlgWarning)
                if self.P is not None:
                    M = -self.P[self.policy, idx]  # I − P_π, one array
                    M[idx, idx] += 1.0
                    M[:, 0] = 1.0
                    lu = sl.lu_factor(M, overwrite_a=True, check_finite=False)
                    sol = sl.lu_solve(lu, r[self.policy, idx], check_finite=False)
                    mu = sl.lu_solve(lu, e0, trans=1, check_finite=False)
                else:
                    sol, mu = self._sparse_solve(r[self.policy, idx], e0)
        except SolverFailed:
            raise
        except (FloatingPointError, np.linalg.LinAlgError, ValueError, sl.LinAlgWarning):
            sol = mu = np.full(S, np.nan)
        except RuntimeError:  # SuperLU: a singular factor
            sol = mu = np.full(S, np.nan)
        if not (np.isfinite(sol).all() and np.isfinite(mu).all()):
            raise SolverFailed(
                "policy evaluation failed: a policy's chain has more than one recurrent class "
                "(recipes/constrained.py solves such models as an LP)"
            )
        gain, h = float(sol[0]), sol.copy()
        h[0] = 0.0
        return gain, h, np.clip(mu, 0.0, None) / np.clip(mu, 0.0, None).sum()

    def _sparse_solve(self, rhs: np.ndarray, e0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``_evaluate``'s two solves on the sparse chain (SuperLU; singular: RuntimeError)."""
        from scipy import sparse
        from scipy.sparse.linalg import splu

        S = len(self.policy)
        M = (sparse.identity(S, format="csr") - self.rows[self.policy * S + np.arange(S)]).tocsc()
        cut = M.indptr[1]  # column 0 becomes ones, the gain's column
        data = np.concatenate([np.ones(S), M.data[cut:]])
        rows = np.concatenate([np.arange(S, dtype=M.indices.dtype), M.indices[cut:]])
        M = sparse.csc_matrix((data, rows, np.r_[0, M.indptr[1:] - cut + S]), shape=(S, S))
        try:
            lu = splu(M)
        except MemoryError:
            raise SolverFailed(
                f"the LU of the sparse chain of S = {grouped(S)} states does not fit in memory "
                f"({grouped(M.nnz)} non-zeros before fill-in): a smaller env.queue_capacity"
            ) from None
        return lu.solve(rhs), lu.solve(e0, trans="T")

    def _expect(self, h: np.ndarray) -> np.ndarray:
        """[A, S]: P_a h for every action."""
        if self.P is not None:
            return np.asarray(self.P @ h)
        return np.asarray(self.rows @ h).reshape(-1, len(h))

    def _line(self, pol: np.ndarray, mu: np.ndarray) -> Line:
        idx = np.arange(len(pol))
        T, C = float(mu @ self.J[pol, idx]), float(mu @ self.c[pol, idx]) - self.bound
        return pol.copy(), T, C, mu

    def _cross(self) -> None:
        assert self.lo is not None and self.hi is not None
        (_, tl, cl, _), (_, th, ch, _) = self.lo, self.hi
        self.lam = max((tl - th) / (cl - ch), 0.0)
        self.policy = self.lo[0].copy()
        self.seen.clear()

    def _improve(self, improved: np.ndarray) -> None:
        """Policy iteration's move to ``improved``, which in exact arithmetic never returns to a
        policy it has left (where it does, the evaluations cannot rank the actions)."""
        self.seen.add(_key(self.policy))
        if _key(improved) in self.seen:
            raise SolverFailed(
                f"policy iteration came back to a policy it had left (stage {self.stage}, "
                f"λ = {self.lam:.6g}): the chain's evaluations are not accurate enough to rank "
                "the actions (recipes/constrained.py solves such models as an LP)"
            )
        self.policy = improved

    def _result(self, parts: list[tuple[float, np.ndarray, np.ndarray]]) -> LPResult:
        """The mixture of (weight, policy, stationary distribution) parts as the LP's result."""
        A, S = self.J.shape
        x = np.zeros((A, S))
        for w, pol, mu in parts:
            x[pol, np.arange(S)] += w * np.where(self._recurrent(pol, mu), mu, 0.0)
        x /= x.sum()
        occ = torch.from_numpy(x)
        mass = occ.sum(0)
        policy = torch.zeros(S, A, dtype=torch.float64)
        visited = mass > 0
        policy[visited] = (occ[:, visited] / mass[visited]).T
        policy[~visited, -1] = 1.0
        value = float((x * self.J).sum())
        return LPResult(occupancy=occ, policy=policy, value=value, message="dual: optimal")

    def _recurrent(self, pol: np.ndarray, mu: np.ndarray) -> np.ndarray:
        """[S] whether each state is in ``pol``'s recurrent class: one of more than ``DUST`` of
        ``mu`` is, one of less (the LU's dust on transient states) if the chain reaches it."""
        small, out, S = np.flatnonzero(mu <= DUST), mu > DUST, len(pol)
        if not small.size:
            return out
        P = self.P
        rows = P[pol, np.arange(S)] if P is not None else self.rows[pol * S + np.arange(S)]
        into = rows[:, small] > 0  # [S, k]: the moves into the small states
        reached = frontier = np.asarray(into[np.flatnonzero(out)].sum(0)).ravel() > 0
        while frontier.any():
            frontier = (np.asarray(into[small[frontier]].sum(0)).ravel() > 0) & ~reached
            reached = reached | frontier
        out[small] = reached
        return out

    def step(self) -> LPResult | None:
        """One policy evaluation (and improvement, or a step of the walk); the result once the
        optimum is reached.

        Raises:
            InfeasibleTarget: no policy keeps the constraint.
            SolverFailed: a singular chain, a policy iteration that comes back to a policy it
                has left, or more than ``MAX_EVALUATIONS`` evaluations.
        """
        if self.evaluations >= MAX_EVALUATIONS:
            raise SolverFailed(f"the dual planner took more than {MAX_EVALUATIONS} evaluations")
        r = self._reward()
        with one_blas_thread():
            gain, h, mu = self._evaluate(r)
            q = r + self._expect(h)  # [A, S]
        self.evaluations += 1
        if self.stage == 3:
            return self._walk_step(self._line(self.policy, mu))
        S = len(self.policy)
        line = self._line(self.policy, mu)
        if self.stage == 1 and line[2] <= KEEP_TOL:  # a keeping policy is all the search needs
            self.hi, self.stage = line, 2
            self._cross()
            return None
        best = q.max(0)
        optimal = q >= best - TIE_TOL * max(1.0, float(np.abs(best).max()))
        keep = optimal[self.policy, np.arange(S)]
        improved = np.where(keep, self.policy, q.argmax(0))
        if not np.array_equal(improved, self.policy):
            self._improve(improved)
            return None
        if self.stage == 0:
            if line[2] <= KEEP_TOL:
                return self._result([(1.0, self.policy, mu)])
            # the constraint kept best, from the policy that keeps it best one step ahead
            self.lo, self.stage, self.policy = line, 1, self.c.argmin(0)
            self.seen.clear()
            return None
        if self.stage == 1:
            raise InfeasibleTarget(
                f"no policy keeps the constraint: the least it reaches is {line[2]:.3g} over "
                "its bound"
            )
        assert self.lo is not None and self.hi is not None
        crossing = self.lo[1] - self.lam * self.lo[2]
        if gain <= crossing + TIE_TOL * max(1.0, abs(crossing)) or (
            np.array_equal(self.policy, self.lo[0]) or np.array_equal(self.policy, self.hi[0])
        ):
            # both ends are optimal at λ*: walk between them through the policies that attain
            # λ*'s maximum everywhere (each end with its own action wherever that attains it)
            def attaining(pol: np.ndarray) -> np.ndarray:
                return np.where(optimal[pol, np.arange(S)], pol, self.policy)

            self.stage, self.walk = 3, None
            self.toward, self.policy = attaining(self.lo[0]), attaining(self.hi[0])
            return None
        if line[2] > KEEP_TOL:
            self.lo = line
        else:
            self.hi = line
        self._cross()
        return None

    def _mix(self, breaking: Line, keeping: Line) -> LPResult:
        """The two policies' occupation measures mixed so that C binds (C ≤ KEEP_TOL counts as
        kept)."""
        (pb, _, cb, mb), (pk, _, ck, mk) = breaking, keeping
        w = min(max(-ck / (cb - ck), 0.0), 1.0)  # the breaking policy's weight
        return self._result([(w, pb, mb), (1.0 - w, pk, mk)])

    def _walk_step(self, line: Line) -> LPResult | None:
        """The walk at λ*, given the line of the policy just evaluated: the result once switching
        one state breaks the constraint (or the two ends' mixture, where the walk cannot start or
        finish). From its last keeping policy it switches the ``stride`` states that policy visits
        most among those that differ: twice as many after a keeping policy, half as many after a
        breaking one, until one state breaks it."""
        assert self.toward is not None
        if self.walk is None:  # its keeping end
            if line[2] > KEEP_TOL:
                return self._ends()
            self.walk, self.stride = line, 1
        elif line[2] <= KEEP_TOL:
            self.walk, self.stride = line, 2 * self.switched
        elif self.switched == 1:
            return self._mix(line, self.walk)
        else:
            self.stride = self.switched // 2
        base, mu = self.walk[0], self.walk[3]
        differ = np.flatnonzero(base != self.toward)
        if not differ.size:  # the breaking end keeps the constraint after all
            return self._ends()
        top = differ[np.argsort(-mu[differ], kind="stable")[: self.stride]]
        self.switched = len(top)
        self.policy = base.copy()
        self.policy[top] = self.toward[top]
        return None

    def _ends(self) -> LPResult:
        assert self.lo is not None and self.hi is not None
        return self._mix(self.lo, self.hi)

    def advance(self, evaluations: int) -> LPResult | None:
        """Up to ``evaluations`` steps; the result as soon as it is reached, else None."""
        for _ in range(evaluations):
            out = self.step()
            if out is not None:
                return out
        return None

    def solve(self) -> LPResult:
        """Every step to the end."""
        while (out := self.step()) is None:
            pass
        return out

    def state_dict(self) -> dict[str, Any]:
        """Where it stands (the model is the caller's to keep)."""
        return {
            "policy": self.policy.tolist(),
            "stage": self.stage,
            "lam": self.lam,
            "lo": None if self.lo is None else _line_state(self.lo),
            "hi": None if self.hi is None else _line_state(self.hi),
            "walk": None if self.walk is None else _line_state(self.walk),
            "toward": None if self.toward is None else self.toward.tolist(),
            "stride": self.stride,
            "switched": self.switched,
            "evaluations": self.evaluations,
            "seen": sorted(self.seen),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Go on from ``state_dict``'s point."""
        self.policy = np.asarray(state["policy"], dtype=np.int64)
        self.stage, self.lam = int(state["stage"]), float(state["lam"])
        self.evaluations = int(state["evaluations"])

        def line(v: Any) -> Line | None:
            if v is None:
                return None
            return (np.asarray(v[0], dtype=np.int64), float(v[1]), float(v[2]), np.asarray(v[3]))

        self.lo, self.hi, self.walk = line(state["lo"]), line(state["hi"]), line(state.get("walk"))
        toward = state.get("toward")
        self.toward = None if toward is None else np.asarray(toward, dtype=np.int64)
        self.stride, self.switched = int(state.get("stride", 1)), int(state.get("switched", 1))
        self.seen = set(state.get("seen", []))


def _key(policy: np.ndarray) -> str:
    return hashlib.blake2b(policy.tobytes(), digest_size=16).hexdigest()


def _line_state(line: Line) -> tuple[list[int], float, float, list[float]]:
    return line[0].tolist(), line[1], line[2], line[3].tolist()


def solve_dual(model: ExactMDP, objective: torch.Tensor, constraint: Constraint) -> LPResult:
    """The LP's optimum of ``objective`` subject to ``constraint`` on ``model``, by
    ``DualPlanner`` to the end on ``chain(model)``."""
    return DualPlanner(chain(model), objective, constraint).solve()


def solve_cmdp_dual(
    model: ExactMDP, target_miss: float, objective: str = "throughput"
) -> CMDPSolution:
    """``irdrc.core.cmdp.solve_cmdp`` for the miss target alone, on the LP's dual (``solve_dual``):
    the policy's exact metrics, the states it randomises in and those it never visits, and the
    dual's own value as ``lp_value``.

    Raises:
        ValueError: on a bad value (named).
        InfeasibleTarget: when no policy meets the target.
    """
    from irdrc.core.exact import stationary_metrics

    table = objective_table(model, objective)
    constraint = build_constraints(model, target_miss)[0]
    try:
        result = solve_dual(model, table, constraint)
    except InfeasibleTarget as e:
        raise InfeasibleTarget(f"target_miss={target_miss:g} is out of reach: {e}") from None
    metrics = stationary_metrics(model, result.policy.to(model.device))
    achieved = {"miss_detection": (metrics.miss_detection, float(target_miss))}
    return CMDPSolution.of(result, objective, metrics, achieved, result.value)
