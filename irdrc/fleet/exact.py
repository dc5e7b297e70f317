"""The exact fleet MDP of MODEL.md § C on factored kernels, and its centralised optimum.

N vehicles (each with a single-vehicle model: alike, or differing in probabilities, rates and
rewards) share road r and weather w; each has its own queue, channel, speed, object (and traffic
phase). The joint state is
(r, w, x_1, …, x_N) with x_i the vehicle's own components, index mixed radix with (r, w) most
significant, then vehicle 1 … N in the single-vehicle order of their components. The joint action
a = Σ_i a_i·2^(i−1) (bit i − 1 is vehicle i's: 0 comm, 1 radar).

The kernels come from the single-vehicle exact model (``irdrc.core.model.build_model``), which is
held to the simulator by its own tests: its transition factorises as P_rw(r′w′ | rw)·K_a(x′ | x)
(road and weather follow their chains whatever the vehicle does), and K_a as the queue's
Q_a(d′ | d, f) times the other components' F_a(f′ | f) — both checked when the model is built. A
vehicle denied the uplink moves its queue as in radar mode (nothing sent) and its components as in
comm mode (no radar reaction). Nothing here is an S × S matrix: the Bellman operator contracts the
value tensor [RW, X, …, X] one axis at a time.

Rewards, events and detection (per vehicle, given the joint action and who is granted):
e = P(event | r, w, v_i, m_i); k_i = other vehicles in radar; q_i = 1 − (1 − share)^k_i the chance
that another vehicle detects vehicle i's event (cooperative perception); P_d, P_fa the radar's.

| a_i | outcome | reward | missed |
|---|---|---|---|
| radar | event, detected by itself (P_d) | r4·(b_i + 1) | 0 |
| radar | event, not by itself, by another (q_i) | 0 | 0 |
| radar | event, by nobody | −r3 | 1 |
| radar | no event, false alarm (P_fa) | −r5 | 0 |
| comm, granted | no event, or an event another vehicle detects | r_comm[c_i] | 0 |
| comm, denied | no event, or an event another vehicle detects | 0 | 0 |
| comm | event, by nobody | −r3 | 1 |
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, field

import torch

from irdrc.core.env import decode_state
from irdrc.core.metrics import Metrics
from irdrc.core.model import build_model
from irdrc.core.params import Params, check_choice, check_number

ACCESS = ("scheduled", "collision")
"""Uplink access rules: ``scheduled`` (K of the requests granted at random when more ask) or
``collision`` (no request granted when more than K ask)."""

FLEET_STATE_LIMIT = 2_000_000
"""The largest joint state space the exact fleet model is built for (value tensors of float64 per
joint action; N = 2 on the paper's sizes has 30 976 states, N = 3 2 725 888 — beyond it)."""


@dataclass(frozen=True)
class FleetSpec:
    """A fleet of identical vehicles (MODEL.md § C).

    Attributes:
        vehicle: each vehicle's single-vehicle model (vehicle 1's with ``per_vehicle``).
        vehicles: N.
        channels: K, uplink channels at the base station.
        access: ``scheduled`` or ``collision`` (``ACCESS``).
        share: the probability that another vehicle in radar mode detects a vehicle's event.
        per_vehicle: None (every vehicle is ``vehicle``), or N single-vehicle models where the
            vehicles differ — in their probabilities, rates and rewards; their state spaces, the
            shared road and weather chains and the horizon must be the same (``FleetModel``
            checks).
    """

    vehicle: Params = field(default_factory=Params)
    vehicles: int = 2
    channels: int = 1
    access: str = "scheduled"
    share: float = 0.5
    per_vehicle: tuple[Params, ...] | None = None

    def __post_init__(self) -> None:
        check_number("env.vehicles", self.vehicles, 1, 16, integer=True)
        check_number("env.channels", self.channels, 1, 16, integer=True)
        check_choice("env.access", self.access, ACCESS)
        check_number("env.share", self.share, 0.0, 1.0)
        if self.per_vehicle is not None:
            per = tuple(self.per_vehicle)
            if len(per) != self.vehicles:
                raise ValueError(
                    f"{len(per)} per-vehicle models for env.vehicles={self.vehicles}: give one "
                    "value per vehicle"
                )
            object.__setattr__(self, "per_vehicle", per)
            object.__setattr__(self, "vehicle", per[0])

    @property
    def vehicle_params(self) -> tuple[Params, ...]:
        """Each vehicle's single-vehicle model."""
        return self.per_vehicle or (self.vehicle,) * self.vehicles

    @property
    def alike(self) -> bool:
        """Whether every vehicle has the same model."""
        return len(set(self.vehicle_params)) == 1


def grants(comm: tuple[int, ...], channels: int, access: str) -> list[tuple[float, frozenset]]:
    """The uplink's outcomes when the vehicles ``comm`` ask for it: (probability, granted set).
    At most ``channels`` requests are all granted; beyond, ``scheduled`` grants ``channels`` of
    them uniformly at random and ``collision`` none."""
    if len(comm) <= channels:
        return [(1.0, frozenset(comm))]
    if access == "collision":
        return [(1.0, frozenset())]
    sets = list(itertools.combinations(comm, channels))
    return [(1.0 / len(sets), frozenset(s)) for s in sets]


class VehicleTables:
    """One vehicle's kernels and expectations on the fleet's [RW, X] grid, from its single-vehicle
    exact model (see the module docstring: the factorisations are checked here).

    Attributes:
        single: the vehicle's single-vehicle exact model.
        P_rw: [RW, RW] the road and weather chain it implies.
        K: {"comm", "radar", "denied"} → [X, X] the vehicle's kernel.
    """

    def __init__(self, params: Params, model: FleetModel) -> None:
        single = build_model(params)
        self.single = single
        RW, X, F = model.RW, model.X, model.F
        D1 = params.env.queue_capacity + 1
        grid = model.index
        P = single.P[:, grid.reshape(-1)][:, :, grid.reshape(-1)]
        P = P.reshape(2, RW, X, RW, X)
        self.P_rw = P[0, :, 0].sum(-1)  # [RW, RW′] from any x
        kern = []
        for a in (0, 1):
            K = P[a, 0, :, :, :].sum(1)  # [X, X′] from rw = 0
            want = self.P_rw[:, None, :, None] * K[None, :, None, :]
            if not torch.allclose(P[a], want, atol=1e-12, rtol=0):
                raise ValueError("the single-vehicle model does not factorise over (r, w)")
            kern.append(K)
        # queue × other components: K_a[(d, f), (d′, f′)] = Q_a[(d, f), d′]·F_a[f, f′]
        split = [k.reshape(D1, F, D1, F) for k in kern]
        Q = [k.sum(3) for k in split]  # [D1, F, D1′]
        Fk = [k.sum(2)[0] for k in split]  # [F, F′] from d = 0
        for k, q, f in zip(split, Q, Fk, strict=True):
            if not torch.allclose(k, q[:, :, :, None] * f[None, :, None, :], atol=1e-12, rtol=0):
                raise ValueError("the single-vehicle kernel does not factorise into queue × rest")
        denied = (Q[1][:, :, :, None] * Fk[0][None, :, None, :]).reshape(X, X)
        self.K = {"comm": kern[0], "radar": kern[1], "denied": denied}
        cols = model.cols
        self.event = single.event[grid]  # [RW, X]
        env, rew = params.env, params.reward
        b = (cols[:, 2] + cols[:, 3] + cols[:, 4] + cols[:, 5]).to(torch.float64)[grid]
        channel = params.factor("channel")
        self.r_comm = torch.tensor(channel.comm_reward, dtype=torch.float64)[cols[:, 1][grid]]
        self.detect_reward = rew.r4 * (b + 1.0)
        self.r3, self.r5 = float(rew.r3), float(rew.r5)
        self.p_detect, self.p_alarm = float(env.detection_prob), float(env.false_alarm_prob)
        self.sent = {"comm": single.sent[0][grid], "radar": single.sent[1][grid]}
        self.dropped = {"comm": single.dropped[0][grid], "radar": single.dropped[1][grid]}
        self.capacity = single.capacity[0][grid]
        self.queue = single.queue.to(torch.float64)[grid]

    def terms(
        self, act: int, others_radar: int, granted: bool, share: float
    ) -> dict[str, torch.Tensor]:
        """The vehicle's expected reward, missed events, events, sent, dropped, capacity, comm and
        denied steps per step ([RW, X]) given its action, how many others watch the road, whether
        its uplink request is granted, and the fleet's ``share``."""
        e = self.event
        q = 1.0 - (1.0 - share) ** others_radar  # another vehicle detects the event
        zero = torch.zeros_like(e)
        if act == 1:
            nobody = (1.0 - self.p_detect) * (1.0 - q)
            reward = e * (self.p_detect * self.detect_reward - nobody * self.r3)
            reward = reward - (1.0 - e) * self.p_alarm * self.r5
            return {
                "reward": reward,
                "missed": e * nobody,
                "event": e,
                "sent": self.sent["radar"],
                "dropped": self.dropped["radar"],
                "capacity": zero,
                "radar": torch.ones_like(e),
                "comm": zero,
                "denied": zero,
                "queue": self.queue,
            }
        r_ok = self.r_comm if granted else zero
        reward = (1.0 - e) * r_ok + e * (q * r_ok - (1.0 - q) * self.r3)
        key = "comm" if granted else "radar"  # a denied vehicle's queue moves as in radar mode
        return {
            "reward": reward,
            "missed": e * (1.0 - q),
            "event": e,
            "sent": self.sent[key],
            "dropped": self.dropped[key],
            "capacity": self.capacity if granted else zero,
            "radar": zero,
            "comm": torch.ones_like(e),
            "denied": zero if granted else torch.ones_like(e),
            "queue": self.queue,
        }


class FleetModel:
    """The exact fleet model of ``spec`` (see the module docstring).

    Attributes:
        spec: the fleet.
        single: vehicle 1's single-vehicle exact model.
        RW, X: sizes of the shared (r, w) axis and of one vehicle's own components.
        P_rw: [RW, RW] the road and weather chain.
        tables: each vehicle's ``VehicleTables`` (kernels and expectations; shared where the
            vehicles are alike).
        num_states: RW · X^N.
    """

    def __init__(self, spec: FleetSpec) -> None:
        self.spec = spec
        params = spec.vehicle
        levels = params.env.levels  # (c, r, w, v, m, phases)
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
        self.num_states = self.RW * self.X**self.N
        # single index → (rw, x)
        self.index = torch.empty(self.RW, self.X, dtype=torch.int64)
        self.index[rw, x] = torch.arange(S)
        self.rw_of, self.x_of = rw, x  # single state → (rw, x)
        self.cols = cols
        for i, p in enumerate(spec.vehicle_params):
            for what, a, b in (
                ("state space (env.queue_capacity, the factors' levels)", p.env.levels, levels),
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
                built[p] = VehicleTables(p, self)
        self.tables = [built[p] for p in spec.vehicle_params]
        self.P_rw = self.tables[0].P_rw
        for i, t in enumerate(self.tables):
            if not torch.allclose(t.P_rw, self.P_rw, atol=1e-12, rtol=0):
                raise ValueError(
                    f"vehicle {i + 1}'s road and weather chains (env.stay_good / env.stay_bad of "
                    "road and weather) differ from vehicle 1's: the vehicles share one road"
                )
        self.single = self.tables[0].single
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
                f"env.vehicles={self.N}: {self.num_states:,} joint states, above the exact fleet "
                f"model's {FLEET_STATE_LIMIT:,} (N = 2 on the paper's sizes has 30 976); the "
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
        return self.tables[i].terms(act, others_radar, granted, self.spec.share)

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

    def expected_next(self, V: torch.Tensor, names: list[str]) -> torch.Tensor:
        """E[V(s′) | s] for every joint state when vehicle i moves by kernel ``names[i]``."""
        W = torch.tensordot(self.P_rw, V, dims=([1], [0]))  # [RW, X, …]
        for i, name in enumerate(names):
            W = torch.tensordot(self.tables[i].K[name], W, dims=([1], [1 + i]))  # new axis first
            W = W.movedim(0, 1 + i)
        return W

    def push(self, mu: torch.Tensor, names: list[str]) -> torch.Tensor:
        """The next-step distribution of a (sub-)distribution ``mu`` over joint states moving
        with kernels ``names``."""
        W = torch.tensordot(self.P_rw, mu, dims=([0], [0]))
        for i, name in enumerate(names):
            W = torch.tensordot(self.tables[i].K[name], W, dims=([0], [1 + i])).movedim(0, 1 + i)
        return W

    def reward(self, a: int) -> torch.Tensor:
        """The fleet's expected reward per joint state under joint action ``a``."""
        R = torch.zeros(self.shape(), dtype=torch.float64)
        for p, _, terms in self.joint[a]:
            for i, t in enumerate(terms):
                R = R + p * self._expand(t["reward"], i)
        return R

    def q_values(self, V: torch.Tensor, gamma: float) -> torch.Tensor:
        """Q[a, s] = R_a(s) + γ·E[V(s′)] for every joint action, [2^N, *shape]."""
        out = []
        for a in range(2**self.N):
            Q = self._rewards[a].clone()
            for p, names, _ in self.joint[a]:
                Q = Q + gamma * p * self.expected_next(V, names)
            out.append(Q)
        return torch.stack(out)

    @functools.cached_property
    def _rewards(self) -> list[torch.Tensor]:
        """The fleet's expected reward tensor of every joint action."""
        return [self.reward(a) for a in range(2**self.N)]


@dataclass(frozen=True)
class FleetSolution:
    """The centralised optimum: ``policy`` [S] joint actions (ties → the lowest, all comm first),
    ``values`` [S], ``iterations`` sweeps."""

    policy: torch.Tensor
    values: torch.Tensor
    iterations: int


def value_iteration_fleet(
    model: FleetModel, gamma: float = 0.99, tol: float = 1e-9, max_iter: int = 100_000
) -> FleetSolution:
    """Value iteration over the joint state and the 2^N joint actions until sup |V_{k+1} − V_k|
    < ``tol`` (as ``irdrc.core.solve.value_iteration``)."""
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"gamma={gamma} must be in (0, 1)")
    model.check_exact()
    V = torch.zeros(model.shape(), dtype=torch.float64)
    for it in range(1, max_iter + 1):  # noqa: B007 - reported after the loop
        Q = model.q_values(V, gamma)
        V_new = Q.max(0).values
        if float((V_new - V).abs().max()) < tol:
            V = V_new
            break
        V = V_new
    else:
        raise RuntimeError(f"fleet value iteration did not converge in {max_iter} sweeps")
    Q = model.q_values(V, gamma)
    policy = Q.argmax(0)  # first maximum: the lowest joint action
    return FleetSolution(policy.reshape(-1), V.reshape(-1), it)


FLEET_METRICS = (
    "avg_reward",
    "throughput",
    "miss_detection",
    "radar_fraction",
    "drop_rate",
    "denial_rate",
    "link_capacity",
    "mean_queue",
)
"""Metrics per vehicle and for the fleet (ratios of sums across vehicles)."""


def _as_probs(model: FleetModel, policy: torch.Tensor) -> torch.Tensor:
    """[S, 2^N] joint action probabilities from [S] joint actions or [S, 2^N]."""
    t = torch.as_tensor(policy)
    n = 2**model.N
    if t.shape == (model.num_states,):
        return torch.nn.functional.one_hot(t.long(), n).to(torch.float64)
    if t.shape == (model.num_states, n):
        return t.to(torch.float64)
    raise ValueError(
        f"policy must be [{model.num_states}] joint actions or [{model.num_states}, {n}]"
    )


def _schedule(model: FleetModel, policy) -> list[torch.Tensor]:
    """A stationary policy ([S] joint actions or [S, 2^N] probabilities) or a periodic one (a
    list of them, one per phase) as per-phase probabilities [2^N, *shape]."""
    phases = list(policy) if isinstance(policy, list | tuple) else [policy]
    return [_as_probs(model, p).T.reshape(-1, *model.shape()) for p in phases]


def _step_all(model: FleetModel, mu: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """One step of the fleet chain from ``mu`` under per-state action probabilities ``probs``."""
    nxt = torch.zeros_like(mu)
    for a in range(2**model.N):
        part = mu * probs[a]
        if float(part.sum()) == 0.0:
            continue
        for p, names, _ in model.joint[a]:
            nxt = nxt + p * model.push(part, names)
    return nxt / nxt.sum()


def stationary_fleet(
    model: FleetModel, policy, tol: float = 1e-13, max_iter: int = 200_000
) -> list[torch.Tensor]:
    """The stationary distribution of a joint policy at each of its phases (one for a stationary
    policy; a list of per-phase policies is applied in turn, as round-robin is), by power
    iteration from uniform over whole cycles (one recurrent class assumed, as
    ``irdrc.core.solve.stationary_distribution``)."""
    model.check_exact()
    sched = _schedule(model, policy)
    mu = torch.full(model.shape(), 1.0 / model.num_states, dtype=torch.float64)
    for _ in range(max_iter):
        start, path = mu, []
        for probs in sched:
            path.append(mu)
            mu = _step_all(model, mu, probs)
        if float((mu - start).abs().sum()) < tol:
            return path
    raise RuntimeError(f"the fleet's stationary distribution did not converge in {max_iter} cycles")


PRINTED = (
    "avg_reward",
    "throughput",
    "miss_detection",
    "radar_fraction",
    "denial_rate",
    "drop_rate",
)
"""The columns of a printed fleet table."""


def long_run_rates(s: dict[str, float]) -> dict[str, float]:
    """``FLEET_METRICS`` (but link capacity) from per-step sums of one vehicle's (or the fleet's)
    ``reward``, ``missed``, ``event``, ``sent``, ``dropped``, ``radar``, ``comm``, ``denied``,
    ``queue`` (and ``capacity`` where known)."""
    out = {
        "avg_reward": s["reward"],
        "throughput": s["sent"],
        "miss_detection": s["missed"] / s["event"] if s["event"] > 0 else math.nan,
        "radar_fraction": s["radar"],
        "drop_rate": s["dropped"],
        "denial_rate": s["denied"] / s["comm"] if s["comm"] > 0 else math.nan,
        "mean_queue": s["queue"],
    }
    if "capacity" in s:
        out["link_capacity"] = s["capacity"]
    return out


def fleet_metrics(model: FleetModel, policy) -> tuple[Metrics, list[dict]]:
    """Exact long-run metrics of a joint policy (stationary, or periodic as a list of per-phase
    policies, averaged over its phases): the fleet's ``Metrics`` (reward, throughput, drops and
    capacity summed over the vehicles; miss detection a ratio of sums; radar fraction and mean
    queue averaged over them) and each vehicle's, then the fleet's, as dicts of
    ``FLEET_METRICS``."""
    model.check_exact()
    sched = _schedule(model, policy)
    path = stationary_fleet(model, policy)
    keys = (
        "reward",
        "missed",
        "event",
        "sent",
        "dropped",
        "capacity",
        "radar",
        "comm",
        "denied",
        "queue",
    )
    sums = [dict.fromkeys(keys, 0.0) for _ in range(model.N)]
    for mu, probs in zip(path, sched, strict=True):
        for a in range(2**model.N):
            w = mu * probs[a] / len(sched)
            if float(w.sum()) == 0.0:
                continue
            for p, _, terms in model.joint[a]:
                for i, t in enumerate(terms):
                    for k in keys:
                        sums[i][k] += p * float((w * model._expand(t[k], i)).sum())

    per = [long_run_rates(s) for s in sums]
    total = {k: sum(s[k] for s in sums) for k in keys}
    fleet = long_run_rates(total)
    n = model.N
    fleet_m = Metrics(
        avg_reward=fleet["avg_reward"],
        episode_reward=fleet["avg_reward"] * model.spec.vehicle.env.horizon,
        throughput=fleet["throughput"],
        link_capacity=fleet["link_capacity"],
        miss_detection=fleet["miss_detection"],
        radar_fraction=total["radar"] / n,
        drop_rate=fleet["drop_rate"],
        mean_queue=total["queue"] / n,
    )
    for i, r in enumerate(per):
        r["vehicle"] = i + 1
    per.append(
        {
            "vehicle": "fleet",
            **fleet,
            "radar_fraction": total["radar"] / n,
            "mean_queue": total["queue"] / n,
        }
    )
    return fleet_m, per


def joint_from_single(model: FleetModel, actions: torch.Tensor) -> torch.Tensor:
    """[S_fleet] joint actions where every vehicle applies the single-vehicle table ``actions``
    ([S] over the single model's states) to its own state and the shared road and weather."""
    table = torch.as_tensor(actions).long()[model.index]  # [RW, X]
    joint = torch.zeros(model.shape(), dtype=torch.int64)
    for i in range(model.N):
        joint = joint + (model._expand(table, i) << i)
    return joint.reshape(-1)


def joint_policy(model: FleetModel, table: torch.Tensor) -> torch.Tensor:
    """[S_fleet] joint actions of a decentralised policy: a table [S] over the single-vehicle
    states every vehicle applies to its own state, one per vehicle [N·S] (vehicle-major), or
    already a joint action per joint state [S_fleet]."""
    S, table = model.single.num_states, torch.as_tensor(table).long().reshape(-1)
    if table.numel() == S:  # one table every vehicle applies
        return joint_from_single(model, table)
    if table.numel() == model.num_states:  # a joint action per joint state
        return table
    if table.numel() != model.N * S:
        raise ValueError(
            f"a fleet policy has {S}, {model.N * S} or {model.num_states} entries, not "
            f"{table.numel()}"
        )
    per = table.reshape(model.N, S)  # vehicle i's own table (agent_index)
    return sum((joint_from_single(model, per[i]) >> i & 1) << i for i in range(model.N))


def single_optima(model: FleetModel, gamma: float = 0.99) -> torch.Tensor:
    """[N, S] each vehicle's own single-vehicle optimum (value iteration on its model alone)."""
    from irdrc.core.solve import value_iteration

    done: dict[int, torch.Tensor] = {}
    for t in model.tables:
        if id(t) not in done:
            done[id(t)] = value_iteration(t.single, gamma=gamma).policy
    return torch.stack([done[id(t)] for t in model.tables])


def baselines(model: FleetModel, single_optimum: torch.Tensor) -> dict[str, object]:
    """MODEL.md § C's baselines as joint policies: every vehicle applying the single-vehicle
    optimum ``single_optimum`` ([S], or its own [N, S]: ``single_optima``) to its own state; round-robin in phase (all comm, then all radar)
    and in anti-phase (odd and even vehicles alternate the other way round); a sensing rotation
    (vehicle t mod N in radar at step t, the others in comm). Periodic ones are lists of per-phase
    joint actions."""
    S, N = model.num_states, model.N
    every = 2**N - 1

    def const(a: int) -> torch.Tensor:
        return torch.full((S,), a, dtype=torch.int64)

    odd = sum(1 << i for i in range(1, N, 2))  # vehicles 2, 4, … (bits 1, 3, …)
    return {
        "N copies of the single optimum": joint_policy(model, single_optimum.reshape(-1)),
        "round-robin in phase": [const(0), const(every)],
        "round-robin in anti-phase": [const(odd), const(every ^ odd)],
        "sensing rotation": [const(1 << t) for t in range(N)],
    }
