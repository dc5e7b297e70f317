"""One vehicle learning from its own stream (MODEL.md § E): the loop every learner on one stream runs.

Episodes of the paper's length follow one another on one ``VehicleStream``. At each step the learner
acts on the state and sees what the step produced; at each episode's end it does its end-of-episode
work, the ``Ledger`` adds the episode's periods (each with the behaviour policy in force and what
the stream recorded in it: one period per episode, or more where the learner announces
within-episode changes of its behaviour, ``StreamLearner.switches``, or reports one from
``observe``), and, every
``eval_every_frames`` env steps, the greedy policy is scored exactly. Checkpoints fall between
episodes: the learner's whole state (its replay included), the stream's generator and the ledger, so
a resumed run goes on exactly as the uninterrupted one would.

The loop also times every decision as a vehicle acting in real time would wait for it: the
learner's work between one step's outcome and its next action (``observe``, then ``act``, and
``switch``, ``end_episode`` and ``begin_episode`` where they fall between the two). The exact
scoring (the ledger's, the greedy policy's, and the ``behaviour`` table the ledger reads) and the
simulated step itself are left out. The run's slowest decision and the number of decisions over
``SLOW_DECISION`` go into its ``info``.
"""

from __future__ import annotations

import itertools
import time
from typing import Any

import torch

from irdrc.agents.base import Hooks, RunRecord, progress_record
from irdrc.core.params import Params
from irdrc.core.stream import OwnStream, Step, VehicleStream
from irdrc.online.ledger import Ledger, Tally


class StreamLearner:
    """What a learner on one stream supplies to the loop (subclasses override what they need).

    Attributes:
        name: the profile's name.
        updates: learning updates so far (gradient steps, plans, table updates).
    """

    name: str = "learner"
    updates: int = 0

    def begin_episode(self, episode: int) -> None:
        """Before the episode's first step (0-based ``episode``)."""

    def switches(self, episode: int, horizon: int) -> tuple[int, ...]:
        """Steps ``0 < t < horizon`` of the episode after which the behaviour policy changes
        (``switch`` is called there); the ledger scores each period between them with the policy
        in force. A change it does not announce (a gradient step) is scored with the policy of the
        period's start, unless ``observe`` reports it."""
        return ()

    def switch(self, steps: int) -> None:
        """At each announced step: change the behaviour policy (``steps`` the stream's steps so
        far)."""

    def act(self, state: int) -> int:
        """The behaviour's action in ``state`` (exploration included)."""
        raise NotImplementedError(f"{type(self).__name__} must define act(state) -> 0 or 1")

    def observe(self, state: int, action: int, step: Step) -> bool | None:
        """What the step from ``state`` with ``action`` produced. A true return says its
        behaviour policy changes from the next step on (a plan made while it acted is ready):
        the ledger scores the steps before and after with their own policies, as at an announced
        switch."""

    def end_episode(self, episode: int) -> dict[str, float]:
        """After the episode's last step; returns scalars to log (``train/…``)."""
        return {}

    def behaviour(self) -> torch.Tensor:
        """[S, A] the behaviour policy now: what ``act`` draws from."""
        raise NotImplementedError(f"{type(self).__name__} must define behaviour() -> [S, A]")

    def greedy(self) -> torch.Tensor:
        """The policy it would deploy if learning stopped now: [S] actions or [S, A]
        probabilities."""
        raise NotImplementedError(f"{type(self).__name__} must define greedy() -> [S] or [S, A]")

    def info(self) -> dict[str, Any]:
        """Facts worth reporting at the end (e.g. where its time went)."""
        return {}

    def state_dict(self) -> dict[str, Any]:
        """Everything it needs to go on exactly (between episodes)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore ``state_dict``."""


def planning_report(
    unit: str, per_step: int, lags: list[int], begun: int, pending: bool
) -> dict[str, Any]:
    """``info()``'s ``planning`` entry of a learner that plans beside its acting: ``per_step``
    units of work a step (named by ``unit``), the plans that came into force and their lags (steps
    from their data to their coming into force), and the plans begun but replaced by a newer one
    before they were ready (``pending``: one is being made now)."""
    ready = sorted(lags)
    return {
        "planning": {
            unit: per_step,
            "plans_made_beside_acting": len(ready),
            "plan_lag_steps_median": ready[len(ready) // 2] if ready else None,
            "plan_lag_steps_max": ready[-1] if ready else None,
            "plans_superseded": begun - len(ready) - int(pending),
        }
    }


def _scored(score: Any, source: str, *args: Any) -> Any:
    """``score(*args)`` (a scorer's ``metrics``, the ledger's ``add``), a table that is not a
    policy of the scenario's states refused naming the learner's method that gave it."""
    try:
        return score(*args)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from err


RESUME_KEYS = ("episode", "learner", "stream", "ledger", "history")
"""What a checkpoint of a run on one stream holds (besides the counters every learner's has)."""

SLOW_DECISION = 1e-3
"""A decision that took longer than this (seconds) is counted (``info["decisions_over_1ms"]``)."""


def learn_on_stream(
    learner: StreamLearner,
    params: Params,
    scorer: Any,
    *,
    episodes: int,
    seed: int = 0,
    eval_every_frames: int | None = None,
    hooks: Hooks | None = None,
    resume: dict[str, Any] | None = None,
    greedy_scorer: Any = None,
    stream: Any = None,
) -> RunRecord:
    """Run ``learner`` on one vehicle's stream for ``episodes`` episodes.

    Args:
        learner: the learner.
        params: the scenario.
        scorer: its exact scorer: the ledger's behaviour policies and the greedy policy.
        episodes: episodes of the stream (``env.horizon`` steps each).
        seed: the stream's seed (the learner seeds its own randomness).
        eval_every_frames: the greedy policy is scored at the end of the first episode reaching
            each multiple of this many env steps, and at the end (default: every episode).
        hooks: ``on_eval`` with each evaluation's record (``PROGRESS_FIELDS`` and the ledger's
            ``LEDGER_FIELDS``), ``on_batch`` after each episode, ``on_checkpoint`` every
            ``checkpoint_every_frames`` env steps, ``should_stop`` after each episode.
        resume: a checkpoint (``RunRecord.state``) to go on from.
        greedy_scorer: scores the greedy policy's row (default ``scorer``); its ``extra(table)``,
            where it has one, adds columns (the safe learner's objective against the LP's).
        stream: where the steps come from (default: the simulator, ``VehicleStream(params,
            seed)``): any object with ``reset() -> state`` and ``step(action) -> Step``
            (``irdrc.core.stream.OwnStream`` says what it is held to). The ledger's exact columns
            still score each behaviour policy on ``params``' model; the realised ones count what
            this stream produced.

    Returns:
        The record: ``history`` one row per evaluation, ``greedy`` [1, S] the final greedy policy
        (its most likely action), ``policy`` [1, S, A] where that policy randomises, ``state`` the
        final checkpoint, ``info`` the ledger's final row and where the time went.
    """
    hooks = hooks or Hooks()
    greedy_scorer = greedy_scorer or scorer
    scored = getattr(getattr(scorer, "model", None), "params", None)
    if scored is not None and scored != params:
        raise ValueError(
            "the scorer is another scenario's: the ledger scores this stream on "
            "exact_scorer(params), the model of the scenario it runs on"
        )
    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes={episodes!r} must be an integer >= 1")
    stream = VehicleStream(params, seed) if stream is None else OwnStream(stream, params)
    T = stream.horizon
    every = int(eval_every_frames or T)
    if every < 1:
        raise ValueError(f"eval.every_frames={every!r} must be >= 1")
    ledger = Ledger(scorer)
    record = RunRecord(method=learner.name, greedy=torch.zeros(1, 1, dtype=torch.int64))
    optimum = greedy_scorer.optimal_metrics.avg_reward
    seconds = dict.fromkeys(
        ("episode_start", "act_and_learn", "episode_end", "ledger", "evaluate"), 0.0
    )
    start = 0
    worst, slow = 0.0, 0  # the slowest decision (s) and the decisions over SLOW_DECISION
    t0 = time.perf_counter()
    if resume is not None:
        missing = [k for k in RESUME_KEYS if k not in resume]
        if missing:
            raise ValueError(
                f"resume: the checkpoint has no {', '.join(missing)}: not a checkpoint of a "
                "learner on one stream"
            )
        start = int(resume["episode"])
        timing = resume.get("decisions", {})  # absent from checkpoints written before it
        worst, slow = float(timing.get("worst", 0.0)), int(timing.get("slow", 0))
        learner.load_state_dict(resume["learner"])
        stream.load_state_dict(resume["stream"])
        ledger.load_state_dict(resume["ledger"])
        record.history = list(resume["history"])
        record.episode_rewards = list(resume.get("episode_rewards", []))
        t0 -= float(resume["wall_seconds"])

    def evaluate(done: int) -> None:
        e0 = time.perf_counter()
        table = learner.greedy()
        row = progress_record(
            0,
            done * T,
            done,
            time.perf_counter() - t0,
            learner.updates,
            _scored(greedy_scorer.metrics, f"{learner.name}.greedy()", table),
            optimum,
        )
        row.update(ledger.row())
        extra = getattr(greedy_scorer, "extra", None)
        if extra is not None:
            row.update(extra(table))
        record.history.append(row)
        hooks.eval([row])
        seconds["evaluate"] += time.perf_counter() - e0

    def state(done: int) -> dict[str, Any]:
        return {
            "episode": done,
            "frames": done * T,
            "updates": learner.updates,
            "wall_seconds": time.perf_counter() - t0,
            "learner": learner.state_dict(),
            "stream": stream.state_dict(),
            "ledger": ledger.state_dict(),
            "history": list(record.history),
            "episode_rewards": list(record.episode_rewards),
            "decisions": {"worst": worst, "slow": slow},
        }

    if resume is None:
        evaluate(0)
    next_eval = (start * T // every + 1) * every
    act, observe, clock = learner.act, learner.observe, time.perf_counter
    held = 0.0  # the learner's work towards the next decision, done outside the steps' loop
    for episode in range(start, episodes):
        b0 = clock()
        learner.begin_episode(episode)
        cuts = [*learner.switches(episode, T), T]
        if any(not 0 < c < d for c, d in itertools.pairwise(cuts)):
            raise ValueError(f"{learner.name}: switches {cuts[:-1]} must rise within (0, {T})")
        a0 = clock()
        held += a0 - b0
        behaviour = learner.behaviour()
        scoring = clock() - a0
        s = stream.reset()
        total, t = Tally(), 0
        since = clock()
        cut = cuts.pop(0)
        while t < T:
            tally = Tally()
            changed: bool | None = False
            while t < cut and not changed:
                a = act(s)
                waited = clock() - since + held
                held = 0.0
                if waited > SLOW_DECISION:
                    slow += 1
                if waited > worst:
                    worst = waited
                try:
                    out = stream.step(a)
                except ValueError as err:  # an action that is neither comm nor radar
                    raise ValueError(f"{learner.name}.act({s}) returned {a!r}: {err}") from err
                since = clock()
                changed = observe(s, a, out)
                tally.reward += out.reward
                tally.events += out.event
                tally.missed += out.missed
                tally.sent += out.sent
                tally.dropped += out.dropped
                s = out.state
                t += 1
            l0 = clock()
            held += l0 - since
            tally.steps = t - total.steps
            _scored(ledger.add, f"{learner.name}.behaviour()", behaviour, tally)
            total += tally
            if t < T:
                w0 = clock()
                scoring += w0 - l0
                if t == cut:
                    learner.switch(episode * T + cut)
                    cut = cuts.pop(0)
                l0 = clock()
                held += l0 - w0
                behaviour = learner.behaviour()
                since = clock()
            scoring += clock() - l0
        a1 = clock()
        scalars = learner.end_episode(episode)
        held += clock() - a1
        seconds["episode_start"] += a0 - b0
        seconds["act_and_learn"] += a1 - a0 - scoring
        seconds["ledger"] += scoring
        seconds["episode_end"] += clock() - a1
        done = episode + 1
        record.episode_rewards.append(
            {"learner": 0, "episode": done, "env_steps": done * T, "reward": total.reward}
        )
        hooks.batch({"env_steps": done * T, "episodes": done, **scalars})
        stop = hooks.stop_requested()
        if done * T >= next_eval or done == episodes or stop:
            evaluate(done)
            next_eval = (done * T // every + 1) * every
        if hooks.checkpoint_due((done - 1) * T, done * T) and done < episodes:
            hooks.checkpoint(state(done))
        if stop:
            record.interrupted = True
            break
    done = len(record.episode_rewards)
    final = learner.greedy()
    if final.dim() == 2:
        record.policy = final[None].to(torch.float64)
        final = final.argmax(-1)
    record.greedy = final[None].long()
    record.env_steps = record.updates = done * T
    record.updates = learner.updates
    record.episodes = done
    record.wall_seconds = time.perf_counter() - t0
    record.state = state(done)
    record.info["ledger"] = ledger.row()
    record.info.update(learner.info())
    for phase, secs in seconds.items():
        record.info[f"seconds_{phase}"] = secs
    record.info["seconds_slowest_decision"] = worst
    record.info["decisions_over_1ms"] = slow
    return record
