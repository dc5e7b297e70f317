"""The config sections recipes share, as typed pieces of their configs: the scenario (``env`` +
``reward``), the evaluation, the logger, checkpoints, plots, the executor of runs, and the run's
common keys. Each checks its values on construction, naming the key; pure Python (torch only to
check a CUDA device, when one is asked for: ``irdrc.runs.limits``).
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, field
from typing import Any

from irdrc.core import checks
from irdrc.core.params import Params
from irdrc.fleet.config import fleet_from_config, is_fleet
from irdrc.fleet.spec import FleetSpec
from irdrc.runs.limits import check_device
from irdrc.runs.scenarios import fleet_scenarios, list_scenarios

BACKENDS = ("none", "csv", "tensorboard", "wandb")
WANDB_MODES = ("auto", "online", "offline", "disabled")
PLOT_FORMATS = ("png", "pdf", "svg")
"""Formats of a run's figures (``plot.format``)."""

MC_LIMIT_STEPS = 1e6
"""A Monte-Carlo evaluation steps its batch ``env.horizon`` times per round (~0.1 ms a step here):
above this many batched steps it is refused."""

FLEET_RECIPES = "recipes/fleet.py (learners) or recipes/solve.py (its optimum)"


def one_vehicle(data: Any, prefix: str = "") -> Params:
    """The scenario of a recipe that takes one vehicle (a fleet refused, naming the fleet's
    recipes)."""
    if is_fleet(data):
        n = (data.get("env") or {}).get("vehicles")
        raise ValueError(
            f"the scenario is a fleet of {n} vehicles (env.vehicles={n}); this recipe takes one "
            f"vehicle — run the fleet with {FLEET_RECIPES}"
        )
    params = Params.from_config({"env": data.get("env", {}), "reward": data.get("reward", {})})
    rw = params.reward
    if rw.r1 == rw.r2 == rw.r3 == rw.r4 == 0:
        import warnings

        warnings.warn("reward.r1 … r4 are all 0: every policy is optimal", stacklevel=2)
    return params


def one_or_fleet(data: Any, prefix: str = "") -> Params | tuple[FleetSpec, str]:
    """One vehicle's ``Params``, or a fleet and what its vehicles observe."""
    if is_fleet(data):
        return fleet_from_config(data)
    return one_vehicle(data, prefix)


def a_fleet(data: Any, prefix: str = "") -> tuple[FleetSpec, str]:
    """A fleet scenario (``env=fleet``) and what its vehicles observe."""
    return fleet_from_config(data)


ONE_VEHICLE = {"keys": ("env", "reward"), "build": one_vehicle}
ONE_OR_FLEET = {"keys": ("env", "reward"), "build": one_or_fleet}
A_FLEET = {"keys": ("env", "reward"), "build": a_fleet}
"""Metadata of a config field built from the ``env`` and ``reward`` sections (``scenario_field``)."""


def scenario_field(metadata: dict[str, Any] = ONE_VEHICLE) -> Any:
    """A config field built from the ``env`` and ``reward`` sections when the config is loaded
    (``metadata``: ``ONE_VEHICLE``, ``ONE_OR_FLEET`` or ``A_FLEET``):
    ``params: Params = scenario_field()``. Before that it holds None."""
    return field(default=None, metadata=metadata)


def seeds(key: str, value: Any, empty: bool = False) -> tuple[int, ...]:
    """A list of distinct seeds (non-empty unless ``empty``): a repeated seed is one run twice."""
    out = checks.check_list(key, value, checks.numbers(0, 2**32 - 1, integer=True), empty=empty)
    repeated = sorted({s for s in out if out.count(s) > 1})
    if repeated:
        raise ValueError(f"{key}={list(out)} repeats seed {repeated[0]}: the same run twice")
    return out


def check_speeds(key: str, speeds: tuple[float, ...], params: Params) -> None:
    """``speeds``, values of ``env.p1.speed`` a recipe sets one by one (``key``), each one the
    scenario ``params`` takes; else a ``ValueError`` naming ``key`` and the value that draws the
    scenario as it is (where ``env.factors.speed`` gives the speed its own levels)."""
    for speed in speeds:
        try:
            params.with_overrides({"env.p1.speed": speed})
        except ValueError as err:
            raise ValueError(
                f"{key}={list(speeds)} sets env.p1.speed one value at a time, and on this "
                f"scenario {err}; {key}=[{params.env.p1.speed:g}] takes the scenario as it is"
            ) from None


def one_vehicle_scenarios(key: str, value: Any, empty: bool = False) -> tuple[str, ...]:
    """A list of named scenarios (``irdrc/scenarios/``) of one vehicle each: a fleet is refused,
    naming the fleet's recipes."""
    fleets = fleet_scenarios()
    allowed = [n for n in list_scenarios() if n not in fleets]
    out = checks.check_list(key, value, empty=empty, distinct=True)
    for i, name in enumerate(out):
        if name in fleets:
            raise ValueError(
                f"{key}[{i}]={name!r} is a fleet of vehicles; here each run is one vehicle "
                f"({', '.join(allowed)}) — a fleet runs in recipes/fleet.py, recipes/solve.py "
                "and recipes/bench_fleet.py"
            )
        checks.check_choice(f"{key}[{i}]", name, allowed)
    return out


@dataclass(frozen=True)
class Eval:
    """``eval.*``: the exact evaluation period (env steps) and the Monte-Carlo evaluation at the
    end (``mc_episodes`` episodes in batches of ``mc_num_envs``; 0 skips it). A recipe without a
    key leaves it None."""

    every_frames: int | None = None
    mc_episodes: int | None = None
    mc_num_envs: int | None = None

    def __post_init__(self) -> None:
        for key, lo, hi in (
            ("every_frames", 1, 10**12),
            ("mc_episodes", 0, 10**7),
            ("mc_num_envs", 1, 10**6),
        ):
            if getattr(self, key) is not None:
                checks.check_numbers(self, "eval.", ((key, lo, hi, checks.INT),))

    @property
    def mc_batch(self) -> int:
        """Envs per Monte-Carlo batch: ``mc_num_envs`` (1 in a recipe without the key)."""
        return self.mc_num_envs or 1

    def check_cost(self, params: Params) -> None:
        """Refuse a Monte-Carlo evaluation that would run for long (``MC_LIMIT_STEPS``)."""
        if not self.mc_episodes:
            return
        steps = math.ceil(self.mc_episodes / self.mc_batch) * params.env.horizon
        if steps > MC_LIMIT_STEPS:
            raise ValueError(
                f"eval.mc_episodes={self.mc_episodes} of env.horizon={params.env.horizon} steps: "
                f"{steps:.2e} batched env steps (~{steps * 1e-4 / 60:.0f} min here, limit "
                f"{MC_LIMIT_STEPS:.0e}); use eval.mc_episodes=0 or a shorter horizon"
            )


PROJECT_FORBIDS = tuple("/\\#?%:")
"""Characters a W&B project name cannot hold (checked before any work, for every backend)."""


@dataclass(frozen=True)
class Logger:
    """``logger=csv|tensorboard|wandb|none`` (``logger.backend``), its W&B ``project`` and
    ``mode`` (auto: online with an API key, offline without one)."""

    backend: str = "csv"
    project: str = "irdrc"
    mode: str = "auto"

    def __post_init__(self) -> None:
        checks.check_choice("logger.backend", self.backend, BACKENDS)
        checks.check_choice("logger.mode", self.mode, WANDB_MODES)
        if isinstance(self.project, int) and not isinstance(self.project, bool):
            object.__setattr__(self, "project", str(self.project))  # logger.project=2026
        bad = sorted(set(str(self.project)) & set(PROJECT_FORBIDS))
        if not isinstance(self.project, str) or not self.project.strip() or bad:
            raise ValueError(
                f"logger.project={self.project!r} must be a name (W&B's project: 1–128 "
                f"characters, none of {' '.join(PROJECT_FORBIDS)})"
            )
        if len(self.project) > 128:
            raise ValueError(f"logger.project={self.project[:20]!r}…: at most 128 characters")


@dataclass(frozen=True)
class Plot:
    """``plot.format``: the format of a run's figures."""

    format: str = "png"

    def __post_init__(self) -> None:
        checks.check_choice("plot.format", self.format, PLOT_FORMATS)


@dataclass(frozen=True)
class Checkpoint:
    """``checkpoint.every_frames``: write ``checkpoint.pt`` every this many env steps, or every
    ``every_seconds`` of wall time, whichever comes first (0 and 0: only at the end and on
    SIGINT/SIGTERM)."""

    every_frames: int = 0
    every_seconds: float = 60.0

    def __post_init__(self) -> None:
        checks.check_numbers(
            self,
            "checkpoint.",
            (("every_frames", 0, 10**12, checks.INT), ("every_seconds", 0, 10**7, {})),
        )


@dataclass(frozen=True)
class Ray:
    """``ray.address`` (local: a private Ray here | auto | HOST:PORT | ray://HOST:PORT) and
    ``ray.num_cpus``."""

    address: str = "local"
    num_cpus: int | None = None

    def __post_init__(self) -> None:
        if self.num_cpus is not None:
            checks.check_numbers(self, "ray.", (("num_cpus", 1, 10**5, checks.INT),))
        if ray_host_port(self.address) is None and self.address not in ("local", "auto"):
            raise ValueError(
                f"ray.address={self.address!r} must be local (a private Ray here), auto (the "
                "cluster this machine belongs to), HOST:PORT or ray://HOST:PORT"
            )


def ray_host_port(address: Any) -> tuple[str, int] | None:
    """The (host, port) of a cluster's Ray address (HOST:PORT or ray://HOST:PORT), else None."""
    host, sep, port = str(address).removeprefix("ray://").rpartition(":")
    return (host, int(port)) if sep and host and port.isdigit() else None


EXECUTOR_KEYS = ("executor", "resume", "cpus_per_trial", "max_failures", "storage_path", "ray")


def ray_installed() -> bool:
    """Whether Ray can be imported here (found, not imported: the check costs nothing)."""
    return importlib.util.find_spec("ray") is not None


@dataclass(frozen=True)
class Executor:
    """How a recipe's many runs execute (the ``executor`` group): on Ray Tune or one after another
    here, rerunning only what did not finish with ``resume``."""

    executor: str = "ray"
    resume: bool = False
    cpus_per_trial: int = 1
    max_failures: int = 0
    storage_path: str | None = None
    ray: Ray = field(default_factory=Ray)

    def __post_init__(self) -> None:
        checks.check_choice("executor", self.executor, ("ray", "local"))
        if self.executor == "ray" and not ray_installed():
            raise ValueError(
                "executor=ray needs Ray Tune, which is not installed: pip install 'irdrc[sweep]' "
                "(in a checkout: bash ci/setup.sh sweep), or executor=local runs the points one "
                "after another in this process"
            )
        checks.check_bool("resume", self.resume)
        checks.check_numbers(
            self,
            "",
            (("cpus_per_trial", 1, 10**4, checks.INT), ("max_failures", 0, 10**4, checks.INT)),
        )


def _executor(data: Any, prefix: str) -> Executor:
    return checks.build(Executor, {k: data[k] for k in EXECUTOR_KEYS if k in data}, prefix)


EXECUTOR = {"keys": EXECUTOR_KEYS, "build": _executor}
"""Metadata of a config field holding the executor group's top-level keys:
``executor: Executor = field(default_factory=Executor, metadata=EXECUTOR)``."""


def check_common(obj: Any) -> None:
    """Check whichever of the keys most recipes share ``obj`` (a recipe's config) has: seed,
    threads, the discount defining the optimum, device, progress, the file name of its table."""
    if hasattr(obj, "seed"):
        checks.check_numbers(obj, "", (("seed", 0, 2**32 - 1, checks.INT),))
    if hasattr(obj, "num_threads"):
        # Above the machine's cores is allowed: ``Run.threads`` caps it (a config runs anywhere).
        checks.check_numbers(obj, "", (("num_threads", 1, 4096, checks.INT),))
    if hasattr(obj, "optimum_gamma"):
        checks.check_numbers(obj, "", (("optimum_gamma", 0, 1, checks.OPEN_HI),))
    if hasattr(obj, "device"):
        check_device(obj.device)
    if hasattr(obj, "progress"):
        checks.check_bool("progress", obj.progress)
    if hasattr(obj, "csv"):
        checks.check_file_name("csv", obj.csv)


def check_eval_period(every: int, total: int, explicit: bool, unit: str = "env steps") -> None:
    """An evaluation period set on purpose longer than the run is a mistake (a profile's default
    period on a run shortened by hand just evaluates at the start and the end)."""
    if every > total and explicit:
        raise ValueError(
            f"eval.every_frames={every} is more than the run's {total} {unit}: only the start "
            "and the end would be evaluated; use a smaller value"
        )


def check_resume(value: Any) -> str | None:
    """``resume`` of a training recipe: a checkpoint's path, or null."""
    if value is not None and not isinstance(value, str):
        raise ValueError(f"resume={value!r} must be a path to a checkpoint.pt (or null)")
    return value or None


@dataclass(frozen=True)
class Learning:
    """The keys every learning recipe shares (``dqn``, ``qlearning``, ``constrained``, ``fleet``):
    its logger, evaluation, checkpoints, seed, threads, the discount defining the optimum, the
    progress bar and the checkpoint it resumes from. A recipe's ``Config`` extends it."""

    logger: Logger = field(default_factory=Logger)
    eval: Eval = field(default_factory=Eval)
    checkpoint: Checkpoint = field(default_factory=Checkpoint)
    seed: int = 0
    optimum_gamma: float = 0.99
    num_threads: int = 1
    progress: bool = True
    resume: str | None = None

    def __post_init__(self) -> None:
        check_common(self)
        object.__setattr__(self, "resume", check_resume(self.resume))


@dataclass(frozen=True)
class OneVehicleLearning(Learning):
    """A single-vehicle learner's recipe keys (``dqn``, ``sac``): the scenario, its figures'
    format and the torch device, beside ``Learning``'s; a recipe's ``Config`` adds its ``algo``."""

    params: Params = scenario_field()
    plot: Plot = field(default_factory=Plot)
    device: str = "cpu"


def algo_field(config: Any) -> Any:
    """The ``algo`` field of a learner's recipe ``Config``: ``config`` (a learner's hyperparameter
    dataclass with ``from_sections``) built from the ``algo`` and ``network`` sections."""
    return field(
        default_factory=config,
        metadata={
            "keys": ("algo", "network"),
            "build": lambda d, p: config.from_sections(d["algo"], d["network"]),
        },
    )
