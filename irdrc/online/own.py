"""A learner of one's own on ``recipes/online.py``: ``learner=PATH.py:Class`` (a file anywhere) or
``learner=package.module:Class`` (an importable module), a subclass of
``irdrc.online.loop.StreamLearner`` built as ``Class(params, seed=seed, **keys)``. Its ``algo.*``
keys are its constructor's keywords, and ``algo.episodes`` the stream's length; it runs on the same
stream, with the same ledger, files, checkpoints and sweeps as the built-in learners.

The class is loaded where the run is checked (a bad path, class or key is refused before any
work) and again where the learner is built (a sweep's worker), from the spec alone: a file's path
is made absolute, so a resumed run or a sweep's trial finds it from any directory.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import importlib.util
import inspect
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

from irdrc.core import checks
from irdrc.online.configs import DEFAULT_EPISODES
from irdrc.online.loop import StreamLearner

DOC = "docs/ONLINE.md#your-own-learner-on-one-stream"
"""Where a user reads how to write one."""

PLAIN = (bool, int, float, str, type(None))
"""Constructor defaults a run records in ``config.yaml`` (others are left to the constructor)."""


def is_own(learner: Any) -> bool:
    """Whether ``learner=`` names a learner of one's own (``…:Class``)."""
    return isinstance(learner, str) and ":" in learner


@dataclass(frozen=True)
class OwnLearnerConfig:
    """``algo`` of a learner of one's own.

    Attributes:
        learner: its spec, a file's path absolute (``/home/…/mine.py:Mine``).
        episodes: episodes of the stream.
        keys: its constructor's keywords, as given.
        name: the class's ``name`` (``StreamLearner.name``), or the class's own name.
    """

    learner: str
    episodes: int = DEFAULT_EPISODES
    keys: dict[str, Any] = field(default_factory=dict)
    name: str = "learner"

    def __post_init__(self) -> None:
        episodes = checks.check_number("algo.episodes", self.episodes, 1, 10**7, integer=True)
        object.__setattr__(self, "episodes", episodes)


def load_class(spec: str) -> tuple[type[StreamLearner], str]:
    """The class ``spec`` names, and the spec with a file's path made absolute.

    Raises:
        ValueError: a malformed spec, no such file or module, an import that fails, no such
            class, or a class that is not a ``StreamLearner``.
    """
    where, _, attr = spec.rpartition(":")
    if not where or not attr.isidentifier():
        raise ValueError(
            f"learner={spec}: a learner of your own is learner=PATH.py:Class or "
            f"learner=package.module:Class ({DOC})"
        )
    if where.endswith(".py"):
        path = Path(where).expanduser().resolve()
        if not path.is_file():
            raise ValueError(f"learner={spec}: no such file ({path})")
        where = str(path)
        module = _file_module(spec, path)
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as err:
            raise ValueError(
                f"learner={spec}: cannot import {where} ({err}); a file is learner=PATH.py:{attr}"
            ) from None
    cls = getattr(module, attr, None)
    if cls is None:
        near = checks.closest(attr, [n for n in vars(module) if not n.startswith("_")])
        hint = f" (did you mean {near}?)" if near else ""
        raise ValueError(f"learner={spec}: {Path(where).name} has no {attr}{hint}")
    if not (isinstance(cls, type) and issubclass(cls, StreamLearner)):
        raise ValueError(
            f"learner={spec}: {attr} is not a subclass of irdrc.online.loop.StreamLearner ({DOC})"
        )
    return cls, f"{where}:{attr}"


def _file_module(spec: str, path: Path) -> Any:
    """The module of the file ``path``, imported once per process and content under a name of its
    own (its ``if __name__ == "__main__":`` part does not run; a file edited since is imported
    again), its directory on the import path while it is imported."""
    digest = hashlib.sha256(str(path).encode() + b"\0" + path.read_bytes())
    name = "irdrc_own_" + digest.hexdigest()[:16]
    if name in sys.modules:
        return sys.modules[name]
    found = importlib.util.spec_from_file_location(name, path)
    if found is None or found.loader is None:
        raise ValueError(f"learner={spec}: {path} is not a Python module")
    module = importlib.util.module_from_spec(found)
    sys.modules[name] = module
    sys.path.insert(0, str(path.parent))  # its neighbours import, as under python PATH.py
    try:
        found.loader.exec_module(module)
    except (Exception, SystemExit) as err:  # its top level ran sys.exit(): not a module to load
        del sys.modules[name]
        raise ValueError(
            f"learner={spec}: importing {path.name} failed: {type(err).__name__}: {err}"
        ) from None
    finally:
        with contextlib.suppress(ValueError):  # unless its own code took it off
            sys.path.remove(str(path.parent))
    return module


def _keywords(cls: type) -> dict[str, inspect.Parameter]:
    """The constructor's keywords besides ``params`` and ``seed``."""
    parameters = list(inspect.signature(cls).parameters.values())[1:]
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    return {p.name: p for p in parameters if p.kind in kinds and p.name != "seed"}


def own_learner_config(spec: str, algo: Any) -> OwnLearnerConfig:
    """The ``algo`` of the learner ``spec`` (``algo.episodes`` and its constructor's keywords),
    checked against its constructor ``Class(params, seed=…, **keys)``.

    Raises:
        ValueError: a bad spec (``load_class``), a constructor that takes no ``seed``, a key it
            does not take (naming the closest) or a keyword it needs and was not given.
    """
    cls, spec = load_class(spec)
    data = dict(algo or {})
    episodes = data.pop("episodes", DEFAULT_EPISODES)
    signature = inspect.signature(cls)
    if "seed" not in signature.parameters:
        raise ValueError(
            f"learner={spec}: its constructor must take (params, seed=…, **keys): the run seeds it"
        )
    keywords = _keywords(cls)
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in signature.parameters.values())
    if not takes_any:
        checks.reject_unknown_keys("algo.", data, [*keywords, "episodes"])
    try:
        signature.bind(None, seed=0, **data)
    except TypeError as err:
        raise ValueError(f"learner={spec}: {cls.__name__}(params, seed=…, algo.*): {err}") from None
    name = cls.name if cls.name != StreamLearner.name else cls.__name__
    return OwnLearnerConfig(spec, episodes, data, name)


def recorded_keys(cfg: OwnLearnerConfig) -> dict[str, Any]:
    """``algo`` as a run of ``cfg`` records it: ``episodes``, the constructor's plain defaults and
    the keys given over them."""
    cls, _ = load_class(cfg.learner)
    defaults = {
        n: p.default
        for n, p in _keywords(cls).items()
        if p.default is not inspect.Parameter.empty and isinstance(p.default, PLAIN)
    }
    return {"episodes": cfg.episodes, **defaults, **cfg.keys}


def make_own_learner(cfg: OwnLearnerConfig, params: Any, seed: int) -> StreamLearner:
    """The learner ``cfg`` names, built for the scenario ``params``.

    Raises:
        ValueError: its constructor failed (naming it and the error).
    """
    cls: Any = load_class(cfg.learner)[0]  # a subclass's constructor: (params, seed=…, **keys)
    try:
        learner = cls(params, seed=seed, **cfg.keys)
    except Exception as err:
        raise ValueError(
            f"learner={cfg.learner}: {cls.__name__}(params, seed={seed}, …) failed: "
            f"{type(err).__name__}: {err}"
        ) from err
    return cast(StreamLearner, learner)


def resumable(cfg: OwnLearnerConfig) -> bool:
    """Whether the learner keeps its state in a checkpoint (it defines ``state_dict``)."""
    cls, _ = load_class(cfg.learner)
    return cls.state_dict is not StreamLearner.state_dict
