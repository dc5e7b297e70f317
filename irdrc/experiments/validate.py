"""Every recipe's config checked before any work: keys, values, combinations and cost.

``check_overrides`` runs on the command line before Hydra composes anything: an unknown key (with or
without ``+``) fails with the closest valid key. ``validate(name, cfg)`` runs on the composed config
(of a recipe, or of every point of a sweep before any trial starts) and raises a ``ValueError``
naming the key and the allowed range; what would exhaust memory or run for hours is refused with
its estimated cost.
"""

from __future__ import annotations

import difflib
import math
import os
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from irdrc.agents import dqn, qlearning
from irdrc.core.model import DENSE_MODEL_LIMIT_BYTES
from irdrc.core.params import Params, check_bool, check_choice, check_number, to_plain
from irdrc.experiments.config import CONF_DIR, compose, list_scenarios
from irdrc.experiments.finish import PLOT_FORMATS
from irdrc.experiments.grid import candidate_overrides, override_key, parse_grid
from irdrc.experiments.guard import load_resume
from irdrc.experiments.runs import RUNNERS, batch_points
from irdrc.experiments.tracking import BACKENDS, WANDB_MODES
from irdrc.fleet.config import is_fleet

EPISODIC_LIMIT_FLOPS = 2e11
"""Exact episodic metrics step a distribution through ``env.horizon`` matrix-vector products
(2·S² flops each, one run per policy) unless S is small enough for repeated squaring; above this
estimate they are refused (minutes on this class of machine)."""
MC_LIMIT_STEPS = 1e6
"""A Monte-Carlo evaluation steps its batch ``env.horizon`` times per round (~0.1 ms a step here):
above this many batched steps it is refused."""
SOLVES_LIMIT = 5_000
"""The trade-off's bisection check solves every grid point below its answer: at most this many."""


GENERAL_MODEL_KEYS = (
    "env.factors",
    "env.bursty",
    "env.detection_prob",
    "env.false_alarm_prob",
    "reward.r5",
)
"""Optional keys of the general model (MODEL.md § B): absent from v1 scenarios, so a command line
adds them with ``+`` (``+env.detection_prob=0.9``); ``Params`` validates them."""


def config_groups() -> list[str]:
    """Config groups a command line may choose (``env=…``, ``algo=…``, …)."""
    return sorted(["env", *(p.name for p in CONF_DIR.iterdir() if p.is_dir())])


def flat_keys(node: Any, prefix: str = "") -> set[str]:
    """Every dotted key of a config, mappings included (``eval``, ``eval.every_frames``)."""
    out = set()
    if isinstance(node, dict):
        for k, v in node.items():
            key = f"{prefix}{k}"
            out.add(key)
            out |= flat_keys(v, key + ".")
    return out


OTHER_RECIPE = {
    "dqn": {
        "algo=qlearning": "python recipes/qlearning.py",
        "algo=qlearning_paper": "python recipes/qlearning.py algo=qlearning_paper",
        "algo=dqn_lagrangian": "python recipes/constrained.py learner=dqn_lagrangian",
    },
}
"""Per recipe: group choices that belong to another recipe, and the command to use instead."""

GROUP_USERS = {
    "executor": "python recipes/sweep.py (or a benchmark: bench_robust, bench_constrained)"
}
"""Config groups that only some recipes have, and which ones."""


def check_overrides(config_name: str, overrides: list[str]) -> None:
    """Fail on a key ``recipes/conf/<config_name>.yaml`` does not have (``+key`` included), naming
    the closest valid key, on an unknown scenario or group option, and on a group choice that
    belongs to another recipe (naming it).

    Raises:
        ValueError: the first bad override.
    """
    for o in overrides:
        if o in OTHER_RECIPE.get(config_name, {}):
            raise ValueError(
                f"{o} is not a {config_name} profile: use {OTHER_RECIPE[config_name][o]}"
            )
    groups = config_groups()
    choices = [o for o in overrides if "=" in o and override_key(o) in groups and o[0] not in "+~"]
    rest = [o for o in overrides if o not in choices]
    if any(override_key(o) in GROUP_USERS for o in choices):
        plain = compose(config_name, [])
        for o in choices:
            key = override_key(o)
            if key in GROUP_USERS and key not in plain:
                raise ValueError(f"{config_name} has no {key}: {key}= is for {GROUP_USERS[key]}")
    for o in choices:
        key, value = o.split("=", 1)
        options = (
            list_scenarios()
            if key == "env"
            else sorted(p.stem for p in (CONF_DIR / key).glob("*.yaml"))
        )
        if value not in options:
            raise ValueError(f"{key}={value!r} is not a choice of {key}: {', '.join(options)}")
    base = OmegaConf.to_container(compose(config_name, choices), resolve=False)
    keys = flat_keys(base)
    for o in rest:
        if "=" not in o and not o.startswith("~"):
            raise ValueError(f"{o!r} is not an override: write key=value")
        key = override_key(o)
        if key.startswith("hydra.") or key == "hydra" or key in keys:
            continue
        if "env" in keys and any(key == g or key.startswith(g + ".") for g in GENERAL_MODEL_KEYS):
            continue  # the general model's optional keys (checked with the model's own errors)
        close = difflib.get_close_matches(key, sorted(keys | set(groups)), n=1, cutoff=0.5)
        hint = f"; did you mean {close[0]}?" if close else ""
        raise ValueError(
            f"unknown key {key!r} in {config_name}{hint} ({config_name}.yaml has no such key)"
        )


# -- shared checks ----------------------------------------------------------------------------------


def _opt(cfg: DictConfig, key: str) -> Any:
    """A value by dotted key, or None when absent."""
    return OmegaConf.select(cfg, key, default=None)


def check_device(device: Any) -> str:
    """``device`` if torch can use it here (``cpu``, or ``cuda[:n]`` with a CUDA device)."""
    import torch

    if not isinstance(device, str):
        raise ValueError(f"device={device!r} must be cpu or cuda")
    try:
        dev = torch.device(device)
    except RuntimeError as err:
        raise ValueError(f"device={device!r} is not a torch device (cpu, cuda, cuda:0 …)") from err
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device={device}: no CUDA device here (use device=cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device={device}: only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        raise ValueError(f"device={device!r} must be cpu or cuda")
    return device


def check_writable_dir(key: str, path: Any) -> Path:
    """``path`` as a directory this process can create files in (created if missing)."""
    p = Path(str(path)).expanduser()
    try:
        p.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=p, prefix=".irdrc-write-test-"):
            pass
    except OSError as err:
        raise ValueError(f"{key}={path}: cannot write there ({err.strerror or err})") from err
    return p


def check_params(cfg: DictConfig, factored: bool = False) -> Params:
    """The model (``env``, ``reward``), and what the exact solver can afford for it: the dense
    model up to ``DENSE_MODEL_LIMIT_BYTES``, or with ``factored`` (recipes that switch to the
    factored operator for large S) any S the configuration allows."""
    params = Params.from_config(cfg)
    S = params.env.num_states
    dense = 16 * S * S
    if dense > DENSE_MODEL_LIMIT_BYTES and not factored:
        raise ValueError(
            f"env.queue_capacity={params.env.queue_capacity}: the exact model has S = {S} states "
            f"and its dense transition tensor would take {dense / 2**30:.1f} GiB (limit "
            f"{DENSE_MODEL_LIMIT_BYTES / 2**30:.1f} GiB); use env.queue_capacity ≤ "
            f"{int(math.sqrt(DENSE_MODEL_LIMIT_BYTES / 16) // math.prod(params.env.levels)) - 1}"
        )
    rw = params.reward
    if rw.r1 == rw.r2 == rw.r3 == rw.r4 == 0:
        warnings.warn("reward.r1 … r4 are all 0: every policy is optimal", stacklevel=2)
    return params


def check_episodic_cost(params: Params, key: str = "env.horizon") -> None:
    """Refuse exact episodic metrics that would run for long (see ``EPISODIC_LIMIT_FLOPS``)."""
    from irdrc.core.solve import DOUBLING_MAX_STATES

    S, T = params.env.num_states, params.env.horizon
    if S <= DOUBLING_MAX_STATES:
        return  # repeated squaring: log2(T) matrix products
    flops = 2.0 * S * S * T * 5
    if flops > EPISODIC_LIMIT_FLOPS:
        raise ValueError(
            f"{key}={T} with S = {S} states: exact episodic metrics would take ~{flops:.1e} flops "
            f"(limit {EPISODIC_LIMIT_FLOPS:.0e}); use a shorter horizon"
        )


def check_common(cfg: DictConfig, factored: bool = False, fleet: bool = False) -> Params | None:
    """Keys most recipes share: seed, device, threads, discount, evaluation, progress, logger
    (``factored``: see ``check_params``). With ``fleet`` a fleet scenario is checked as one
    (``check_fleet``; None is returned); without, a fleet is refused naming the fleet's recipes."""
    if fleet and "env" in cfg and is_fleet(cfg):
        check_fleet(cfg)
        params = None
    else:
        params = check_params(cfg, factored) if "env" in cfg else None
    if "seed" in cfg:
        check_number("seed", cfg.seed, 0, 2**32 - 1, integer=True)
    if "device" in cfg:
        check_device(cfg.device)
    if "num_threads" in cfg:
        check_number("num_threads", cfg.num_threads, 1, os.cpu_count() or 1, integer=True)
    if "optimum_gamma" in cfg:
        check_number("optimum_gamma", cfg.optimum_gamma, 0, 1, open_hi=True)
    if _opt(cfg, "eval.every_frames") is not None:
        check_number("eval.every_frames", cfg.eval.every_frames, 1, 10**12, integer=True)
    if _opt(cfg, "eval.mc_episodes") is not None:
        check_number("eval.mc_episodes", cfg.eval.mc_episodes, 0, 10**7, integer=True)
    if _opt(cfg, "eval.mc_num_envs") is not None:
        check_number("eval.mc_num_envs", cfg.eval.mc_num_envs, 1, 10**6, integer=True)
    if params is not None and _opt(cfg, "eval.mc_episodes"):
        rounds = math.ceil(int(cfg.eval.mc_episodes) / int(cfg.eval.mc_num_envs))
        batched_steps = rounds * params.env.horizon
        if batched_steps > MC_LIMIT_STEPS:
            raise ValueError(
                f"eval.mc_episodes={cfg.eval.mc_episodes} of env.horizon={params.env.horizon} "
                f"steps: {batched_steps:.2e} batched env steps (~{batched_steps * 1e-4 / 60:.0f} min "
                f"here, limit {MC_LIMIT_STEPS:.0e}); use eval.mc_episodes=0 or a shorter horizon"
            )
    if "progress" in cfg and cfg.progress != "auto":
        check_bool("progress", cfg.progress)
    if _opt(cfg, "plot.format") is not None:
        check_choice("plot.format", cfg.plot.format, PLOT_FORMATS)
    if "logger" in cfg:
        check_choice("logger.backend", cfg.logger.backend, BACKENDS)
        check_choice("logger.mode", cfg.logger.mode, WANDB_MODES)
    if "resume" in cfg and not isinstance(cfg.resume, bool | str | type(None)):
        raise ValueError(f"resume={cfg.resume!r} must be a path (or true/false for sweeps)")
    return params


def _check_eval_period(cfg: DictConfig, total: int, explicit: frozenset[str]) -> None:
    """An evaluation period set on purpose longer than the run is a mistake; a profile's default
    period on a run shortened by hand just evaluates at the start and the end."""
    every = int(cfg.eval.every_frames)
    if every > total and "eval.every_frames" in explicit:
        raise ValueError(
            f"eval.every_frames={every} is more than the run's {total} env steps: only the start "
            "and the end would be evaluated; use a smaller value"
        )


# -- per recipe -------------------------------------------------------------------------------------


def check_fleet(cfg: DictConfig, exact: bool = False):
    """A fleet scenario (``env=fleet``): its keys and values, and with ``exact`` that the exact
    fleet model reaches it. Returns (the fleet model, what each vehicle observes)."""
    from irdrc.fleet.config import fleet_from_config
    from irdrc.fleet.exact import FleetModel

    spec, observe = fleet_from_config(cfg)
    model = FleetModel(spec)
    if exact:
        model.check_exact()
    return model, observe


def _solve(cfg: DictConfig) -> None:
    params = check_common(cfg, factored=True, fleet=True)  # large S: the factored operator
    check_number("tol", cfg.tol, 0, 1, open_lo=True)
    check_number("max_iter", cfg.max_iter, 1, 10**8, integer=True)
    if params is None:  # a fleet: the exact fleet model must reach it
        check_fleet(cfg, exact=True)
    elif 16 * params.env.num_states**2 <= DENSE_MODEL_LIMIT_BYTES:
        check_episodic_cost(params)


def _fleet(cfg: DictConfig) -> None:
    from irdrc.agents import fleet_learners

    check_common(cfg, fleet=True)
    model, observe = check_fleet(cfg)
    check_choice("learner", cfg.learner, fleet_learners.LEARNERS)
    config = fleet_learners.config(str(cfg.learner), cfg.algo, cfg.network)
    fleet_learners.check(str(cfg.learner), model, observe)
    if int(cfg.eval.every_frames) > config.total_frames:
        raise ValueError(
            f"eval.every_frames={cfg.eval.every_frames} is more than the run's "
            f"{config.total_frames} fleet steps; use a smaller value"
        )
    check_number("eval.mc_fleets", cfg.eval.mc_fleets, 2, 10**6, integer=True)
    check_number("eval.mc_steps", cfg.eval.mc_steps, 1, 10**7, integer=True)
    check_number("eval.mc_burn_in", cfg.eval.mc_burn_in, 0, 10**7, integer=True)


def _evaluate(cfg: DictConfig) -> None:
    from irdrc.experiments.evaluation import load_source

    params = check_common(cfg, factored=True)  # any scenario: the factored scorer beyond dense
    load_source(cfg, params)  # exactly one readable checkpoint / policy that fits the scenario


def _dqn(cfg: DictConfig, explicit: frozenset[str] = frozenset()) -> None:
    params = check_common(cfg)
    config = dqn.DQNConfig.from_node(cfg)
    _check_eval_period(cfg, config.total_frames, explicit)
    if _opt(cfg, "checkpoint.every_frames") is not None:
        check_number(
            "checkpoint.every_frames", cfg.checkpoint.every_frames, 0, 10**12, integer=True
        )
    if _opt(cfg, "compare.qlearning_paper") is not None:
        check_bool("compare.qlearning_paper", cfg.compare.qlearning_paper)
    if _opt(cfg, "compare.qlearning_paper"):
        check_writable_dir("cache_dir", cfg.cache_dir)
    load_resume(cfg, explicit)  # the checkpoint readable, no clash, something left to train
    del params


def _qlearning(cfg: DictConfig, explicit: frozenset[str] = frozenset()) -> None:
    params = check_common(cfg)
    config = qlearning.QLearningConfig.from_node(cfg)
    n = check_number("num_learners", cfg.num_learners, 1, 10**6, integer=True)
    points = batch_points(cfg)
    for point in points:
        params.with_overrides(point)
    rows = n * len(points)
    table_bytes = rows * params.env.num_states * 2 * 4 * 2  # Q-values and visit counts, float32
    if table_bytes > 4 * 2**30:
        raise ValueError(
            f"num_learners={n} × {len(points)} scenarios: the Q-tables would take "
            f"{table_bytes / 2**30:.1f} GiB (limit 4 GiB); use fewer learners"
        )
    _check_eval_period(cfg, config.episodes * params.env.horizon, explicit)


def check_executor(cfg: DictConfig) -> None:
    """The executor group's keys (sweeps, figure2, tradeoff)."""
    check_choice("executor", cfg.executor, ("ray", "local"))
    check_bool("resume", cfg.resume)
    check_number("cpus_per_trial", cfg.cpus_per_trial, 1, 10**4, integer=True)
    check_number("max_failures", cfg.max_failures, 0, 10**4, integer=True)
    if cfg.ray.num_cpus is not None:
        check_number("ray.num_cpus", cfg.ray.num_cpus, 1, 10**5, integer=True)


def _sweep(cfg: DictConfig) -> None:
    check_executor(cfg)
    check_choice("method", cfg.method, tuple(RUNNERS))
    if cfg.get("resume") and not cfg.sweep.grid:
        raise ValueError(
            "resume=true goes on with a sweep's stored grid: name its directory with "
            "hydra.run.dir=… (the one the sweep printed)"
        )
    parse_grid(cfg.sweep.grid)


def _bench_dqn(cfg: DictConfig) -> None:
    check_common(cfg)
    overrides = [str(o) for o in cfg.get("overrides", [])]
    for name, extra in candidate_overrides({"candidates": cfg.profiles}).items():
        try:
            check_overrides("dqn", [*extra, *overrides])
            dqn.DQNConfig.from_node(compose("dqn", [*extra, *overrides]))
        except Exception as err:
            raise ValueError(f"profiles.{name}: {str(err).strip().splitlines()[0]}") from err
    stacked = to_plain(cfg.get("stacked", [])) or []
    if not isinstance(stacked, list):
        raise ValueError(f"stacked={stacked!r} must be a list of learner counts")
    for i, k in enumerate(stacked):
        check_number(f"stacked[{i}]", k, 1, 1024, integer=True)
    check_bool("trace_gaps", cfg.get("trace_gaps", False))


def _bench_scale(cfg: DictConfig) -> None:
    from irdrc.experiments.config import list_scenarios

    check_number("tol", cfg.tol, 0, 1, open_lo=True)
    check_number("repeats", cfg.repeats, 1, 1000, integer=True)
    check_number("timeout", cfg.timeout, 1, 10**6)
    check_number("skip_after_seconds", cfg.skip_after_seconds, 0)
    check_bool("gpu", cfg.gpu)
    names = to_plain(cfg.scenarios)
    if not isinstance(names, list) or not names:
        raise ValueError(f"scenarios={names!r} must be a non-empty list of env scenarios")
    for i, name in enumerate(names):
        check_choice(f"scenarios[{i}]", name, tuple(list_scenarios()))
    states = to_plain(cfg.states)
    if not isinstance(states, list) or not states:
        raise ValueError(f"states={states!r} must be a non-empty list")
    for i, v in enumerate(states):
        check_number(f"states[{i}]", v, 64, 32 * 10**6, integer=True)


def _bench_constrained(cfg: DictConfig) -> None:
    check_common(cfg)
    check_executor(cfg)
    check_number("miss_tolerance", cfg.miss_tolerance, 0, 1)
    check_number("objective_share", cfg.objective_share, 0, 1)
    for key, lo, hi, integer in (
        ("seeds", 0, 2**32 - 1, True),
        ("p1_speed", 0, 1, False),
        ("targets", 0, 1, False),
    ):
        values = to_plain(cfg[key])
        if not isinstance(values, list) or not values:
            raise ValueError(f"{key}={values!r} must be a non-empty list")
        for i, v in enumerate(values):
            check_number(f"{key}[{i}]", v, lo, hi, integer=integer)
    candidate_overrides(cfg)
    # every run's full config is composed and checked when the run plans them, before any trial


def _bench_robust(cfg: DictConfig) -> None:
    check_common(cfg)
    check_executor(cfg)
    check_number("threshold", cfg.threshold, 0, 1, open_lo=True)
    seeds = to_plain(cfg.seeds)
    if not isinstance(seeds, list) or not seeds:
        raise ValueError(f"seeds={seeds!r} must be a non-empty list of seeds")
    for i, v in enumerate(seeds):
        check_number(f"seeds[{i}]", v, 0, 2**32 - 1, integer=True)
    for key, lo, hi in (("p1_speed", 0, 1), ("r4", 0, 1e9)):
        values = to_plain(cfg[key])
        if not isinstance(values, list) or not values:
            raise ValueError(f"{key}={values!r} must be a non-empty list")
        for i, v in enumerate(values):
            check_number(f"{key}[{i}]", v, lo, hi)
    # every run's full config is composed and checked when the run plans them, before any trial


def _bench_fleet(cfg: DictConfig) -> None:
    from irdrc.agents.fleet_learners import LEARNERS

    check_executor(cfg)
    for key, choices in (("learners", LEARNERS), ("scale_learners", ("idqn", "vdn", "qmix"))):
        values = to_plain(cfg[key])
        if not isinstance(values, list):
            raise ValueError(f"{key}={values!r} must be a list")
        for i, v in enumerate(values):
            check_choice(f"{key}[{i}]", v, choices)
    for key, lo, hi, integer in (
        ("seeds", 0, 2**32 - 1, True),
        ("scale_seeds", 0, 2**32 - 1, True),
        ("share", 0, 1, False),
        ("channels", 1, 16, True),
        ("vehicles", 1, 16, True),
    ):
        values = to_plain(cfg[key])
        if not isinstance(values, list):
            raise ValueError(f"{key}={values!r} must be a list")
        for i, v in enumerate(values):
            check_number(f"{key}[{i}]", v, lo, hi, integer=integer)
    check_bool("search", cfg.search)
    cell = to_plain(cfg.search_cell)
    if not isinstance(cell, list) or len(cell) != 2:
        raise ValueError(f"search_cell={cell!r} must be [share, channels]")
    check_number("search_sweeps", cfg.search_sweeps, 1, 1000, integer=True)
    check_choice("plot.format", cfg.plot.format, PLOT_FORMATS)
    # every run's full config is composed and checked when the benchmark plans them


def _demo(cfg: DictConfig) -> None:
    check_common(cfg)


def _bench_env(cfg: DictConfig) -> None:
    check_common(cfg)
    check_number("repeats", cfg.repeats, 1, 1000, integer=True)
    check_number("single_steps", cfg.single_steps, 1, 10**8, integer=True)
    for key in ("sizes", "threads"):
        values = to_plain(cfg[key])
        if not isinstance(values, list):
            raise ValueError(f"{key}={values!r} must be a list")
        for i, v in enumerate(values):
            check_number(f"{key}[{i}]", v, 1, 10**8, integer=True)


def _constrained(cfg: DictConfig) -> None:
    from irdrc.core.cmdp import OBJECTIVES, solve_cmdp

    # the LP runs on the factored model (sparse flow constraints) where the dense one is too large;
    # the learner's exact scorer needs the dense one
    params = check_common(cfg, factored=cfg.get("learner", "lp") == "lp")
    check_choice("objective", cfg.objective, OBJECTIVES)
    check_number("target_miss", cfg.target_miss, 0, 1)
    if cfg.max_drop is not None:
        check_number("max_drop", cfg.max_drop, 0)
    if cfg.min_radar is not None:
        check_number("min_radar", cfg.min_radar, 0, 1)
    check_number("optimum_gamma", cfg.optimum_gamma, 0, 1, open_hi=True)
    check_bool("frontier", cfg.frontier)
    learner = cfg.get("learner", "lp")
    check_choice("learner", learner, ("lp", "dqn_lagrangian"))
    if learner == "dqn_lagrangian":
        from irdrc.agents.lagrangian import LagrangianConfig

        LagrangianConfig.from_node(cfg)
        if cfg.frontier:
            raise ValueError("learner=dqn_lagrangian learns one target: use frontier=false")
        for key in ("max_drop", "min_radar"):
            if cfg.get(key) is not None:
                raise ValueError(
                    f"{key}={cfg[key]}: learner=dqn_lagrangian handles target_miss alone "
                    f"(use learner=lp for {key})"
                )
        check_bool("progress", cfg.progress)
    grid = cfg.frontier_grid
    ps = to_plain(grid.p1_speed)
    if not isinstance(ps, list) or not ps:
        raise ValueError(f"frontier_grid.p1_speed={ps!r} must be a non-empty list")
    for i, p in enumerate(ps):
        check_number(f"frontier_grid.p1_speed[{i}]", p, 0, 1)
    check_number("frontier_grid.points", grid.points, 2, 10_000, integer=True)
    lo = check_number("frontier_grid.r4.lo", grid.r4.lo, 0)
    hi = check_number("frontier_grid.r4.hi", grid.r4.hi, lo)
    step = check_number("frontier_grid.r4.step", grid.r4.step, 0, open_lo=True)
    if (hi - lo) / step > 5000:
        raise ValueError(
            f"frontier_grid.r4: {int((hi - lo) / step) + 1} exact solves per p1.speed (> 5 000); "
            "raise frontier_grid.r4.step"
        )
    targets = to_plain(grid.targets)
    if not isinstance(targets, list):
        raise ValueError(f"frontier_grid.targets={targets!r} must be a list")
    for i, t in enumerate(targets):
        check_number(f"frontier_grid.targets[{i}]", t, 0, 1)
    if params is not None and not cfg.frontier:
        # Feasibility is the LP itself: refused here, before the run directory exists.
        from irdrc.experiments.constrained import constraint_kwargs, lp_exact_model

        solve_cmdp(lp_exact_model(params), **constraint_kwargs(cfg))


VALIDATORS: dict[str, Callable[[DictConfig], None]] = {
    "constrained": _constrained,
    "solve": _solve,
    "fleet": _fleet,
    "evaluate": _evaluate,
    "dqn": _dqn,
    "qlearning": _qlearning,
    "sweep": _sweep,
    "bench_dqn": _bench_dqn,
    "bench_env": _bench_env,
    "demo": _demo,
    "bench_robust": _bench_robust,
    "bench_fleet": _bench_fleet,
    "bench_constrained": _bench_constrained,
    "bench_scale": _bench_scale,
}


def validate(config_name: str, cfg: DictConfig, overrides: list[str] | tuple = ()) -> None:
    """Check a composed config of ``config_name`` before any work (see the module docstring).

    ``overrides``: the overrides it was composed with (what the user set on purpose).
    The paper's recipes bring their own checks (``irdrc.paper.figure2.validate_figure2`` …)."""
    check = VALIDATORS.get(config_name)
    if check is None:
        return
    if config_name in ("dqn", "qlearning"):
        check(cfg, frozenset(override_key(o) for o in overrides))
    else:
        check(cfg)
