"""The exact fleet MDP of MODEL.md § C on factored kernels: one more ``ExactMDP``, with 2^N joint
actions, so its centralised optimum and exact metrics come from ``irdrc.core.exact`` like any model's.

N vehicles (each with a single-vehicle model: alike, or differing in probabilities, rates and
rewards) share road r and weather w; each has its own queue, channel, speed, object (and traffic
phase). The joint state is
(r, w, x_1, …, x_N) with x_i the vehicle's own components, index mixed radix with (r, w) most
significant, then vehicle 1 … N in the single-vehicle order of their components. The joint action
a = Σ_i a_i·2^(i−1) (bit i − 1 is vehicle i's: 0 comm, 1 radar).

Each vehicle's kernels and expectations are ``irdrc.fleet.vehicle.VehicleTables`` (the kernels
from its single-vehicle exact model, the rewards table there). Nothing here is an S × S matrix:
each vehicle's kernel is applied to the tensor [RW, X, …, X] on its own axis, as its queue factor
and its other components' chain.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Mapping, Sequence

import torch

from irdrc.core.checks import grouped
from irdrc.core.exact import ExactMDP
from irdrc.core.exact.krylov import stationary_krylov
from irdrc.core.params import Params
from irdrc.core.states import decode_state
from irdrc.fleet.spec import FLEET_STATE_LIMIT, FleetSpec, grants
from irdrc.fleet.vehicle import TERMS, VehicleTables


class FleetModel(ExactMDP):
    """The exact fleet model of ``spec`` (see the module docstring).

    Attributes:
        spec: the fleet.
        single: vehicle 1's single-vehicle exact model.
        RW, X: sizes of the shared (r, w) axis and of one vehicle's own components.
        P_rw: [RW, RW] the road and weather chain.
        kernels: each vehicle's ``VehicleTables`` (kernels and expectations; shared where the
            vehicles are alike).
        num_states: RW · X^N.
    """

    def __init__(self, spec: FleetSpec) -> None:
        self.spec = spec
        params = spec.vehicle
        levels = params.env.factor_levels  # (c, r, w, v, m, phases)
        S = params.env.num_states
        cols = decode_state(torch.arange(S), levels)  # d, c, r, w, v, m[, phase]
        Lr, Lw = levels[1], levels[2]
        self.RW = Lr * Lw
        rw = cols[:, 2] * Lw + cols[:, 3]
        own = [0, 1, 4, 5] + ([6] if cols.shape[1] == 7 else [])  # d, c, v, m[, phase]
        radix = [params.env.queue_capacity + 1, levels[0], levels[3], levels[4]]
        radix += [levels[5]] if cols.shape[1] == 7 else []
        x = torch.zeros(S, dtype=torch.int64)
        for j, n in zip(own, radix, strict=True):
            x = x * n + cols[:, j]
        self.X = math.prod(radix)
        self.F = self.X // radix[0]  # the components besides the queue
        self.N = spec.vehicles
        self._num_states = self.RW * self.X**self.N
        # single index → (rw, x)
        self.index = torch.empty(self.RW, self.X, dtype=torch.int64)
        self.index[rw, x] = torch.arange(S)
        self.rw_of, self.x_of = rw, x  # single state → (rw, x)
        self.cols = cols
        for i, p in enumerate(spec.vehicle_params):
            for what, a, b in (
                (
                    "state space (env.queue_capacity, the factors' levels)",
                    p.env.factor_levels,
                    levels,
                ),
                ("env.queue_capacity", p.env.queue_capacity, params.env.queue_capacity),
                ("env.horizon", p.env.horizon, params.env.horizon),
            ):
                if a != b:
                    raise ValueError(
                        f"vehicle {i + 1}'s {what} differs from vehicle 1's: the vehicles may "
                        "differ in probabilities, rates and rewards, not in their states"
                    )
        built: dict[Params, VehicleTables] = {}
        for p in spec.vehicle_params:
            if p not in built:
                built[p] = VehicleTables(p, self.index, cols)
        self.kernels = [built[p] for p in spec.vehicle_params]
        self.P_rw = self.kernels[0].P_rw
        for i, t in enumerate(self.kernels):
            if not torch.allclose(t.P_rw, self.P_rw, atol=1e-12, rtol=0):
                raise ValueError(
                    f"vehicle {i + 1}'s road and weather chains (env.stay_good / env.stay_bad of "
                    "road and weather) differ from vehicle 1's: the vehicles share one road"
                )
        self.single = self.kernels[0].single
        """Vehicle 1's single-vehicle exact model (every vehicle's state space)."""

    @property
    def exact(self) -> bool:
        """Whether the joint state space is within ``FLEET_STATE_LIMIT`` (the exact solver and
        metrics; the simulator works at any N)."""
        return self.num_states <= FLEET_STATE_LIMIT

    def check_exact(self) -> None:
        """Raise a ``ValueError`` when the joint state space is beyond the exact model's reach."""
        if not self.exact:
            raise ValueError(
                f"env.vehicles={self.N}: {grouped(self.num_states)} joint states, above the exact fleet "
                f"model's {grouped(FLEET_STATE_LIMIT)} (N = 2 on the paper's sizes has 30 976); the "
                "simulator and Monte-Carlo evaluation work at any N"
            )

    @functools.cached_property
    def joint(self) -> list[list[tuple[float, list[str], list[dict[str, torch.Tensor]]]]]:
        """Per joint action, its uplink outcomes (``_joint``), built on first use."""
        self.check_exact()
        return [self._joint(a) for a in range(2**self.N)]

    def vehicle_states(self) -> torch.Tensor:
        """[S, N] every joint state's vehicles as single-vehicle state indices."""
        self.check_exact()
        idx = torch.arange(self.num_states)
        xs = []
        for _ in range(self.N):
            xs.append(idx % self.X)
            idx = idx // self.X
        rw = idx
        return torch.stack([self.index[rw, x] for x in reversed(xs)], 1)

    # -- per joint action -----------------------------------------------------------------------

    def actions_of(self, a: int) -> tuple[int, ...]:
        """Each vehicle's action (0 comm, 1 radar) in joint action ``a``."""
        return tuple((a >> i) & 1 for i in range(self.N))

    def vehicle_terms(
        self, i: int, act: int, others_radar: int, granted: bool
    ) -> dict[str, torch.Tensor]:
        """Vehicle ``i``'s expected reward, missed events, events, sent, dropped, capacity, comm
        and denied steps per step ([RW, X]) given its action, how many others watch the road and
        whether its uplink request is granted (``VehicleTables.terms``)."""
        return self.kernels[i].terms(act, others_radar, granted, self.spec.share)

    def _joint(self, a: int) -> list[tuple[float, list[str], list[dict[str, torch.Tensor]]]]:
        """For joint action ``a``: per uplink outcome, (probability, each vehicle's kernel name,
        each vehicle's expected terms)."""
        acts = self.actions_of(a)
        comm = tuple(i for i, x in enumerate(acts) if x == 0)
        radar = sum(acts)
        out = []
        for p, granted in grants(comm, self.spec.channels, self.spec.access):
            names, terms = [], []
            for i, x in enumerate(acts):
                others = radar - x
                if x == 1:
                    names.append("radar")
                else:
                    names.append("comm" if i in granted else "denied")
                terms.append(self.vehicle_terms(i, x, others, x == 0 and i in granted))
            out.append((p, names, terms))
        return out

    # -- operators ------------------------------------------------------------------------------

    def shape(self) -> tuple[int, ...]:
        """The joint state tensor's shape: [RW, X, …, X]."""
        return (self.RW, *([self.X] * self.N))

    def _expand(self, t: torch.Tensor, i: int) -> torch.Tensor:
        """A vehicle-``i`` quantity [RW, X] broadcast over the joint state."""
        view = [self.RW] + [1] * self.N
        view[1 + i] = self.X
        return t.reshape(view)

    def _move(self, W: torch.Tensor, i: int, name: str, forward: bool) -> torch.Tensor:
        """Vehicle ``i``'s kernel ``name`` applied on its axis of W [RW, X, …, X], as its two
        factors (queue, then the other components): the next-step measure of W (``forward``) or
        the expectation E[W(x′) | x]. This costs (D+1)·F·(D+1 + F) per entry of the other axes,
        not X² = ((D+1)·F)²."""
        Q, F = self.kernels[i].factors[name]
        D1, Fn = Q.shape[0], Q.shape[1]
        V = W.reshape(self.RW * self.X**i, D1, Fn, -1)
        if forward and V.shape[0] <= V.shape[3]:
            # few long rows (vehicle 1's axis): one batched product per row, over the components
            # besides the queue, on strided views (no copy of W)
            Qt = self.kernels[i].queue_by_rest[name]  # [F, D+1′, D+1]
            T = torch.empty(V.shape[0], Fn, D1, V.shape[3], dtype=V.dtype)
            for p in range(V.shape[0]):
                torch.bmm(Qt, V[p].permute(1, 0, 2), out=T[p])
            T = torch.matmul(F.T, T.reshape(V.shape[0], Fn, -1))  # [p, f′, (d′, rest)]
            return T.reshape(V.shape[0], Fn, D1, -1).transpose(1, 2).reshape(W.shape)
        if forward:
            V = torch.einsum("pdfq,dfe->pefq", V, Q)
            V = torch.einsum("pefq,fg->pegq", V, F)
        else:
            V = torch.einsum("fg,pegq->pefq", F, V)
            V = torch.einsum("dfe,pefq->pdfq", Q, V)
        return V.reshape(W.shape)

    def expected_next(self, V: torch.Tensor, names: list[str]) -> torch.Tensor:
        """E[V(s′) | s] for every joint state when vehicle i moves by kernel ``names[i]``."""
        W = torch.tensordot(self.P_rw, V, dims=([1], [0]))  # [RW, X, …]
        for i, name in enumerate(names):
            W = self._move(W, i, name, forward=False)
        return W

    def push(self, mu: torch.Tensor, names: list[str]) -> torch.Tensor:
        """The next-step distribution of a (sub-)distribution ``mu`` over joint states moving
        with kernels ``names``."""
        W = torch.tensordot(self.P_rw, mu, dims=([0], [0]))
        for i, name in enumerate(names):
            W = self._move(W, i, name, forward=True)
        return W

    # -- the ExactMDP interface -------------------------------------------------------------------

    @property
    def params(self) -> Params:
        """Vehicle 1's model (horizon and false-alarm settings every vehicle shares)."""
        return self.spec.vehicle

    @property
    def num_actions(self) -> int:
        """2^N joint actions."""
        return 2**self.N

    @property
    def num_states(self) -> int:
        """RW · X^N."""
        return self._num_states

    @property
    def device(self) -> torch.device:
        """CPU (the fleet's kernels are small)."""
        return torch.device("cpu")

    def reward(self, a: int) -> torch.Tensor:
        """The fleet's expected reward per joint state under joint action ``a``."""
        R = torch.zeros(self.shape(), dtype=torch.float64)
        for p, _, terms in self.joint[a]:
            for i, t in enumerate(terms):
                R = R + p * self._expand(t["reward"], i)
        return R

    @functools.cached_property
    def R(self) -> torch.Tensor:
        """[A, S] the fleet's expected reward."""
        return torch.stack([self.reward(a).reshape(-1) for a in range(self.num_actions)])

    def expect(self, V: torch.Tensor) -> torch.Tensor:
        """[A, S]: E[V(s′) | s, a] for every joint action. The road and weather move first,
        once; every prefix of the vehicles' kernels (``joint``'s names) is applied once and
        shared by the joint actions and uplink outcomes that begin with it."""
        V = torch.tensordot(self.P_rw, V.reshape(self.shape()), dims=([1], [0]))
        moved: dict[tuple[str, ...], torch.Tensor] = {(): V}
        for a in range(self.num_actions):
            for _, names, _ in self.joint[a]:
                for i in range(self.N):
                    key = tuple(names[: i + 1])
                    if key not in moved:
                        moved[key] = self._move(moved[key[:-1]], i, key[-1], forward=False)
        out = torch.zeros(self.num_actions, *self.shape(), dtype=V.dtype)
        for a in range(self.num_actions):
            for p, names, _ in self.joint[a]:
                out[a] += p * moved[tuple(names)]
        return out.reshape(self.num_actions, -1)

    def weights(self, probs: torch.Tensor) -> dict[tuple[str, ...], torch.Tensor]:
        """For ``probs`` [S, 2^N]: per tuple of the vehicles' kernel names, the probability
        [RW, X, …, X] that a joint state's mass moves with those kernels (the joint actions'
        probabilities times their uplink outcomes'); tuples that never occur are left out."""
        out: dict[tuple[str, ...], torch.Tensor] = {}
        for a in range(self.num_actions):
            col = probs[:, a]
            if not bool(col.any()):
                continue
            col = col.reshape(self.shape())
            for p, names, _ in self.joint[a]:
                key = tuple(names)
                out[key] = p * col if key not in out else out[key] + p * col
        return out

    def step(
        self, x: torch.Tensor, probs: torch.Tensor | dict[tuple[str, ...], torch.Tensor]
    ) -> torch.Tensor:
        """x·P_π for ``probs`` [S, 2^N] (or its ``weights``, computed once for many steps). The
        mass moving with the same kernels is summed before they apply; after vehicle i's kernel,
        the parts that move alike from there on are summed again; the road and weather move last,
        once."""
        mu = x.reshape(self.shape())
        weights = probs if isinstance(probs, dict) else self.weights(probs)
        parts = {names: mu * w for names, w in weights.items()}
        for i in range(self.N):
            moved: dict[tuple[str, ...], torch.Tensor] = {}
            for names, W in parts.items():
                W = self._move(W, i, names[0], forward=True)
                rest = names[1:]
                moved[rest] = W if rest not in moved else moved[rest] + W
            parts = moved
        if not parts:
            return torch.zeros_like(x)
        return torch.tensordot(self.P_rw, parts[()], dims=([0], [0])).reshape(-1)

    def cycle(
        self, schedule: Sequence[torch.Tensor], tol: float = 1e-13, max_iter: int = 200_000
    ) -> list[torch.Tensor]:
        """The stationary distribution at each phase of ``schedule`` (one table per phase): that of
        one period's chain by a linear solve (``irdrc.core.exact.krylov.stationary_krylov``; the
        joint queues mix slowly, so power iteration would need ten times the operator products),
        then stepped through the phases."""
        phases = [self.weights(probs) for probs in schedule]

        def period(x: torch.Tensor) -> torch.Tensor:
            for w in phases:
                x = self.step(x, w)
            return x

        start = torch.full((self.num_states,), 1.0 / self.num_states, dtype=torch.float64)
        mu, _ = stationary_krylov(period, start, tol=tol, max_iter=max_iter)
        path = []
        for w in phases:
            path.append(mu)
            mu = self.step(mu, w)
            mu = mu / mu.sum()
        return path

    def sums(self, occ: torch.Tensor, vehicle: int | None = None) -> dict[str, float]:
        """The per-step expectations of a state-action occupancy ``occ`` [A, S]: those of
        ``expected_sums`` under ``fleet_tables`` (or vehicle ``vehicle``'s ``vehicle_tables``),
        without a table over the joint states. A vehicle's terms depend on its own state and the
        road and weather alone, so each is summed against the occupancy's marginal on those."""
        vehicles = range(self.N) if vehicle is None else [vehicle]
        n = self.N if vehicle is None else 1
        occ = occ.to(torch.float64).reshape(self.num_actions, *self.shape())
        keys = ("reward", "missed", "false_alarms", "sent", "dropped", "capacity", "denied", "comm")
        out = dict.fromkeys((*keys, "event", "radar", "quiet_radar", "queue"), 0.0)
        own = self.joint[0][0][2]  # event and queue: the same under every action
        for a in range(self.num_actions):
            total = float(occ[a].sum())
            if total == 0.0:
                continue
            marginal = {}
            for i in vehicles:
                others = [1 + j for j in range(self.N) if j != i]
                marginal[i] = occ[a].sum(others) if others else occ[a]  # [RW, X]
            events = _against(marginal, own, "event")
            out["event"] += events
            out["queue"] += _against(marginal, own, "queue") / n
            radar = sum(self.actions_of(a)[i] for i in vehicles) / n
            if radar:
                out["radar"] += radar * total
                out["quiet_radar"] += radar * (total - events)
            for p, _, terms in self.joint[a]:
                for key in keys:
                    out[key] += p * _against(marginal, terms, key)
        return out

    def vehicle_tables(self, i: int) -> Mapping[str, torch.Tensor]:
        """Vehicle ``i``'s per-step expectations ([A, S]; ``event`` and ``queue`` [S], ``radar``
        [A]), built when read."""
        return _Tables(self, [i], mean=False)

    def fleet_tables(self) -> Mapping[str, torch.Tensor]:
        """The fleet's: sums over the vehicles, and their mean for ``radar`` and ``queue`` (the
        share of the fleet's time in radar mode, the mean queue of a vehicle)."""
        return _Tables(self, list(range(self.N)), mean=True)

    def tables(self) -> Mapping[str, torch.Tensor]:
        """The fleet's expectation tables (``fleet_tables``)."""
        return self.fleet_tables()


def _against(
    marginal: dict[int, torch.Tensor], terms: list[dict[str, torch.Tensor]], key: str
) -> float:
    """Σ over the vehicles i of ``marginal`` (i's occupancy on [RW, X]) times i's term ``key``."""
    return sum(float((m * terms[i][key]).sum()) for i, m in marginal.items())


class _Tables(Mapping[str, torch.Tensor]):
    """Expectation tables of some vehicles of a fleet (summed), each built when read."""

    def __init__(self, model: FleetModel, vehicles: list[int], mean: bool) -> None:
        self.model, self.vehicles, self.mean = model, vehicles, mean

    def __iter__(self) -> Iterator[str]:
        return iter(("R", *TERMS[1:]))

    def __len__(self) -> int:
        return len(TERMS)

    def __getitem__(self, key: str) -> torch.Tensor:
        m = self.model
        n = len(self.vehicles) if self.mean else 1
        if key == "radar":
            bits = torch.tensor([[x for x in m.actions_of(a)] for a in range(m.num_actions)])
            return bits[:, self.vehicles].sum(1).to(torch.float64) / n
        name = "reward" if key == "R" else key
        if name in ("event", "queue"):  # the same under every action
            terms = m.joint[0][0][2]
            t = torch.zeros(m.shape(), dtype=torch.float64)
            for i in self.vehicles:
                t = t + m._expand(terms[i][name], i)
            return (t / (n if name == "queue" else 1)).reshape(-1)
        out = []
        for a in range(m.num_actions):
            t = torch.zeros(m.shape(), dtype=torch.float64)
            for p, _, terms in m.joint[a]:
                for i in self.vehicles:
                    t = t + p * m._expand(terms[i][name], i)
            out.append(t.reshape(-1))
        return torch.stack(out)
