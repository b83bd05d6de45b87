"""A simulated robot learning while it acts: the client's control loop.

Each tick, on an absolute schedule: sense, `act` on the current weights (numpy), pass the
action through the safety layer, execute it, and `learn` the experience (queued, never
blocking). Thinking happens in this process (`--server local`: act-learn-think-MT, or
act-learn-think in lock-step) or on think servers over Zenoh (act-learn-think-C/S). At the end
the run directory holds the weights (with their config), the experiences (the journal in C/S
mode, experiences.npz locally), metrics.json and a learning-curve PNG.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import re
import signal
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from sims.base import Behaviours, Ranges, VecTask
from wfnn_client.brain import Acted, Brain, Experience, LocalBrain
from wfnn_client.config import ClientConfig
from wfnn_client.controllers import LEARNER, Controllers
from wfnn_client.frames import FrameWriter
from wfnn_client.journal import check_task
from wfnn_client.safety import SafetyLayer
from wfnn_client.sims import SIMS, OneBehaviour, SimSpec
from wfnn_client.step import Decided, Learn, Pupil, robot_step
from wfnn_client.tick import Ticker, TickStats
from wfnn_common.config import MAX_SAVED_COUNT, LearnerConfig
from wfnn_common.learners import Learner, make_learner
from wfnn_io.bus import check_exposure
from wfnn_io.cli_errors import handling, interrupt_behind, log_failure, noting, raise_noted, terminate
from wfnn_io.logs import CLIENT_JSON, client_meta, journal_task, remove_empty_log, same_task, task_difference
from wfnn_io.persist import (
    PersistError,
    folders_to_be_made,
    load_checkpoint,
    make_directory,
    read_regular_text,
    remove_empty_folders,
    save_experiences,
    save_figure,
    save_weights,
    to_jsonable,
    writable,
    write_json,
)
from wfnn_io.protocol import EXP_SAFE_ACTION, EXP_VETO_PROPOSED, load_key
from wfnn_io.segments import check_free

log = logging.getLogger(__name__)
_R = TypeVar("_R")

SUITED_REWARD_RMS = (0.05, 20.0)
"""Root-mean-square rewards a step beyond which the deep learner's defaults are known not to suit
the task (README, "a limitation: the reward's scale"): a run meeting such rewards is told once."""
REWARD_ADVICE_AFTER = 1000
"""Finite rewards met before that advice is judged."""


class SetupError(ValueError):
    """The run cannot start as configured (nothing was run); the message says why."""


def learner_config(task: VecTask | Ranges, config: ClientConfig) -> LearnerConfig:
    """The learner's defaults over the declared ranges, with the client's overrides (`overrides`)."""
    extra: dict[str, Any] = {}
    # A sim's advantage k was chosen for the thesis' learner; the deep one starts from its own.
    if config.learner == "thesis" and SIMS[config.sim].advantage_k is not None:
        extra["advantage_k"] = SIMS[config.sim].advantage_k
    if config.symmetries:
        declared = tuple(getattr(task, "symmetries", ()))
        if not declared:
            raise ValueError(f"{config.env or config.sim} declares no symmetries: drop --symmetries")
        extra["symmetries"] = declared
    if config.exploration is not None:
        extra["exploration"] = config.exploration
    base = LearnerConfig.for_task(task, learner=config.learner, seed=config.seed, **extra)
    chosen = config.overrides.apply(base)
    for what, given, task_has in (("state", chosen.state_dim, base.state_dim),
                                  ("action", chosen.action_dim, base.action_dim)):  # fmt: skip
        if given != task_has:  # the task's widths are fixed: a learner of others fails at its first step
            raise ValueError(
                f"the learner options give {given} {what} variables; {config.env or config.sim} has "
                f"{task_has}"
            )
    return chosen


def make_brain(config: ClientConfig, learner: Learner, behaviour: str = "", version: int = 0) -> Brain:
    """Local thinking, or the C/S client over a Zenoh bus (a behaviour of several: its own controller).

    `version`: the last weights version of the run these weights were saved by (local thinking
    counts on from it, so that the runs' journals never name two snapshots by one version).
    """
    if config.local:
        from wfnn_client.brain import LOCAL_SOURCE, Recorder

        # Before the journal is opened: a learner that cannot think here (a device torch does not
        # see) is refused without leaving a journal of its spec behind in the run directory.
        learner.prepare_thinking(compile=config.learn)  # a compile in the think thread held ticks up
        # Off the tick, in lock-step too: a slow disk must not hold up the control loop.
        record = Recorder(config.out / _named("journal", behaviour), learner.config, config.client_id,
                          background=True, task=config.task)  # fmt: skip
        if config.learn:  # its weights are new: numbered past every version the journal names already
            # (given another run's weights, or none, a run numbered from theirs: the versions went back)
            version = max(version, record.journal.last_version.get(LOCAL_SOURCE, -1) + 1)
            if version >= MAX_SAVED_COUNT // 2:  # as the journal's numbering keeps room (`journal.ROOM`)
                record.close()
                raise ValueError(f"journal {record.journal.log.directory} names weights versions up to "
                                 f"{version - 1}, too near the last a run may save ({MAX_SAVED_COUNT - 1}): "
                                 "use another run directory")  # fmt: skip
        try:
            return LocalBrain(learner, lockstep=config.lockstep, think_batch=config.think_batch,
                              recorder=record, learns=config.learn, version=version)  # fmt: skip
        except BaseException:
            record.close()
            raise
    from wfnn_client.remote import RemoteBrain, RemoteConfig, largest_message
    from wfnn_io.bus import ZenohBus

    # Nothing larger than a snapshot of this learner (or a status) is reassembled by Zenoh here.
    largest = largest_message(learner.config) + 1024
    net = dataclasses.replace(config.remote_net, max_message_bytes=min(config.net.max_message_bytes, largest))
    remote = RemoteConfig(
        controller=_named(config.controller, behaviour, "-"), client_id=config.client_id,
        journal_dir=config.out / _named("journal", behaviour), task=config.task,
        key_file=config.key_file, follow=config.follow, lockstep=config.lockstep,
    )  # fmt: skip
    bus = ZenohBus(net)
    try:
        return RemoteBrain(learner, remote, bus, initial=learner.params if config.weights else None)
    except BaseException:
        bus.close()  # an open Zenoh session would hold the process at exit
        raise


StatusCallback = Callable[[dict[str, Any]], None]


def prepare(config: ClientConfig) -> list[str]:
    """Check what a run needs before it starts; -> warnings to show.

    Makes the run directory, reads the key file, and refuses a non-loopback endpoint without a
    key unless `insecure`. The whole config is written there (`config.json`) by `run`, once the
    learners and the weights they start from are known to fit the task.
    """
    make_directory(config.out, "--out names a run directory")
    if config.json_stats is not None and _the_runs_own(Path(config.out), Path(config.json_stats)):
        raise ValueError(
            f"--json-stats {config.json_stats} is one of the run's own files or folders in "
            "--out (journal, weights, experiences, config, metrics, plot, cameras): name another"
        )
    for path in (config.json_stats, config.out / "learning_curve.png", config.out / "metrics.json"):
        if path is not None:
            writable(path)  # now, not when the run is over
    keyed = load_key(str(config.key_file) if config.key_file else None) is not None
    warnings = [] if config.local else check_exposure(config.remote_net, keyed, config.insecure)
    for journal in Path(config.out).glob("journal*"):  # a run already on this directory keeps its record
        check_free(journal)
        if journal.is_dir():  # refused now, as its `Journal` would be, before the task is sent anything
            check_task(journal, client_meta(journal), config.task)
    return warnings


def run(
    config: ClientConfig, on_status: StatusCallback | None = None, prepared: bool = False
) -> dict[str, Any]:
    """Run the simulated robot; returns the metrics also written to `out/metrics.json`.

    `on_status(fields)` is called about twice a second and after every episode. The run
    directory is checked and made first (`prepare`; `prepared`: the caller has done it), and
    the whole config is written there (`config.json`) once nothing else can refuse the start.
    """
    new_folders = [] if prepared else folders_to_be_made(Path(config.out))
    try:
        if not prepared:
            prepare(config)
        spec = SIMS[config.sim]
        task = spec.make(config.sim_options)
        try:
            with _terminated_as_interrupted():
                return _run(config, spec, task, on_status)
        finally:
            close = getattr(task, "close", None)  # a renderer's GL context
            if close is not None:
                close()
    except BaseException:
        remove_empty_folders(new_folders)  # a refused start leaves no empty folder of its own making
        raise


def _terminated_as_interrupted() -> contextlib.AbstractContextManager[None]:
    """SIGTERM (`kill`, a service manager's stop) ends the run as Ctrl-C does, cleanly (`Terminated`).

    By default it ends the process at once: the journal was not closed, so the next run took it
    for a crash and declared the numbers reserved for it lost.
    """
    return handling(terminate, signal.SIGTERM)


def _stop_brains(brains: _Brains) -> int:
    """Stop the brains with SIGTERM and SIGINT only noted meanwhile; -> the first noted, else 0.

    Stopping waits for acks, joins threads and closes the journal and the network session; a
    signal raised in the middle of it (a second Ctrl-C, a supervisor's SIGTERM while the servers
    are silent) left the journal open and the process hung on the session's threads. An ignored
    SIGINT (a job started with &) stays ignored.
    """
    with noting(signal.SIGTERM, signal.SIGINT, keep_ignored=True) as noted:
        brains.stop()
    return noted[0] if noted else 0


@dataclass
class Skill:
    """One learned behaviour of the robot: its learner, and the brain that acts and learns with it."""

    name: str
    """"" for a task's only behaviour."""
    lcfg: LearnerConfig
    learner: Learner
    brain: Brain


_OWN_FILE = re.compile(
    r"(config\.json|metrics\.json|learning_curve\.png|(weights|experiences)(_[^/]*)?\.npz)"
)


def _the_runs_own(out: Path, path: Path) -> bool:
    """Whether `path` is, or is inside, something a run writes in `out` (by any name: links too).

    The run's own files there would be replaced by the stats (a journal segment or weights.npz
    written over with JSON), or the stats by them. The run writes by the names under `out`,
    following links: a journal folder that links to another disk is the run's there too.
    """
    target = Path(os.path.realpath(path))

    def own(name: str, whole: bool) -> bool:  # whole: the name is all of the path below `out`
        return (
            name.startswith("journal")
            or name == "cameras"
            or (whole and _OWN_FILE.fullmatch(name) is not None)
        )

    for base in {Path(os.path.abspath(out)), Path(os.path.realpath(out))}:
        for spelled in (Path(os.path.abspath(path)), target):
            try:
                inside = spelled.relative_to(base)
            except ValueError:
                continue
            if not inside.parts or own(inside.parts[0], len(inside.parts) == 1):
                return True
    for name in os.listdir(out) if os.path.isdir(out) else []:  # where the run's own names lead
        if own(name, True):
            where = Path(os.path.realpath(Path(out) / name))
            if target == where or where in target.parents:
                return True
    return False


def _named(base: str, behaviour: str, sep: str = "_") -> str:
    """`base`, or `base<sep>behaviour` for one behaviour of several."""
    return f"{base}{sep}{behaviour}" if behaviour else base


def _ranges(config: LearnerConfig) -> tuple[tuple[float, ...], ...]:
    return config.state_low, config.state_high, config.action_low, config.action_high


def _learner(config: ClientConfig, name: str, ranges: Ranges) -> tuple[LearnerConfig, Learner, int]:
    """A behaviour's learner config, learner and weights version (from saved weights where given).

    Nothing is written.
    """
    lcfg = learner_config(ranges, config)
    learner = make_learner(lcfg)
    version = 0
    path = _given_weights(config, name)
    if path is not None:
        # A learner that learns here resumes the training saved with the weights (the deep
        # learner's second critic, targets, optimiser and warm-up), as a think server does.
        saved_cfg, params, meta, training = load_checkpoint(path, training=config.learn and config.local)
        kind, same_ranges = saved_cfg.learner, _ranges(saved_cfg) == _ranges(lcfg)
        if kind != lcfg.learner or not same_ranges:
            hint = f": --learner {kind}" if kind != lcfg.learner and same_ranges else ""  # helps only then
            raise ValueError(f"{path} holds weights for spec {saved_cfg.spec_hash()}, this task needs "
                             f"{lcfg.spec_hash()} ({saved_cfg.spec_difference(lcfg)}{hint})")  # fmt: skip
        # The saved network, not the defaults' (a run with another hidden width was refused unless
        # its options were given again); options given that change it are refused.
        resumed = _resumed(saved_cfg, lcfg, config)
        if resumed.spec_hash() != saved_cfg.spec_hash():
            differ = saved_cfg.spec_difference(resumed)
            raise ValueError(f"{path} holds weights for spec {saved_cfg.spec_hash()}; the options given "
                             f"make {resumed.spec_hash()} ({differ})")  # fmt: skip
        _tell_resumed(saved_cfg, resumed, path)
        try:  # weights may be taken to another task of the same spaces (a simulation's to the robot's)
            learned_on = journal_task(meta)
        except ValueError:  # an unreadable record of where they were learned: said as none
            learned_on = None
        if learned_on is not None and not same_task(learned_on, config.task):
            log.warning("%s: weights learned on another task (%s), taken here (their spaces are the same)",
                        path, task_difference(learned_on, config.task))  # fmt: skip
        lcfg = resumed
        try:
            learner = make_learner(lcfg, params=params)
            learner.load_training_state(training)
        except ValueError as exc:  # weights that make no learner of their config (several networks, say)
            raise ValueError(f"{path}: {exc}") from exc
        thinks = meta.get("thinks") if config.local else None
        if thinks is not None:  # the counts go on, the weights' versions after those saved
            learner.thinks[:] = _saved_count(thinks, path, "thinks")
            # Saved before versions were, the thinks bound them (one snapshot per think at most).
            # One more where it learns: the weights saved may have learned after the last snapshot
            # had that number; a run that learns nothing acts on them as they were saved.
            version = max(_saved_count(meta.get("version", thinks), path, "weights version"), thinks)
            version += 1 if config.learn else 0
    return lcfg, learner, version


def _saved_count(value: Any, path: Path, what: str) -> int:
    """`value`, a count saved with the weights at `path`; ValueError where it is none."""
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value < MAX_SAVED_COUNT:
        raise ValueError(f"{path}: its saved {what} is not a count: {repr(value)[:40]}")
    return value


def _resumed(saved: LearnerConfig, chosen: LearnerConfig, config: ClientConfig) -> LearnerConfig:
    """The learner config saved with resumed weights, with what this run's command line sets over it.

    The training goes on as it was configured (its discount, rates, warm-up, seed...): the
    command line's defaults do not replace them. Its overrides (`--thinks`, `--advantage-k`,
    `--bc-weight`, `--learner-options`) and what it gave of `--seed`, `--symmetries` and
    `--exploration` (`config.explicit`) apply, and where the updates run (`PLACEMENT`: this
    host's choice) is this run's.
    """
    changes: dict[str, Any] = {name: getattr(chosen, name) for name in config.explicit}
    if saved.learner == "deep":
        here = chosen.deep
        changes["deep"] = dataclasses.replace(saved.deep, device=here.device, compile=here.compile)
    return config.overrides.apply(dataclasses.replace(saved, **changes))


def _tell_resumed(saved: LearnerConfig, resumed: LearnerConfig, path: Path) -> None:
    """Say which fields of the saved config the command line changes (once the resume is taken)."""
    from wfnn_client.downlink import config_differences

    differ = config_differences(saved.to_json(), resumed.to_json())
    # Said at the default level where the command line changes it: the run's line says "as saved".
    (log.warning if differ else log.info)(
        "%s: resuming its learner config%s", path,
        f", with {', '.join(differ)} as this command line sets them" if differ else "",
    )  # fmt: skip


def _run(
    config: ClientConfig, spec: SimSpec, task: VecTask, on_status: StatusCallback | None
) -> dict[str, Any]:
    rng = np.random.default_rng(config.seed)
    reward_of = spec.reward_of(task) if spec.reward_of else None
    several = spec.behaviours(task, config.sim_options) if spec.behaviours else None
    behaviours: Behaviours = several or OneBehaviour(task, reward_of)
    period = 1.0 / config.tick_hz if config.tick_hz > 0 else 0.0
    ticks = TickStats(keep_all=config.timing_trace)
    ticker = Ticker(period, ticks)
    first = behaviours.ranges(behaviours.names[0])
    # A tick as fast as possible stands for a tick at the task's own real-time rate (`SafetyLayer`).
    simulated_hz = float(getattr(task, "rate_hz", 0.0)) if config.sim == "gym" else 0.0
    simulated_hz = simulated_hz or config.simulated_hz or spec.rate_hz
    safety = SafetyLayer(config.safety, first.action_low, first.action_high, period,
                         spec.veto(task) if spec.veto else None, step_s=1.0 / simulated_hz)  # fmt: skip
    episode_steps = spec.episode_steps(task) if callable(spec.episode_steps) else spec.episode_steps
    tick_count = 0
    skills: list[Skill] = []
    new_journals: list[Path] = []
    controllers: Controllers | None = None
    try:
        learners = [(name, *_learner(config, name, behaviours.ranges(name))) for name in behaviours.names]
        writable(Path(config.out) / "config.json")
        if not config.learn:
            _refuse_a_learning_runs_folder(Path(config.out))
        for name in behaviours.names:  # what the run writes at its end: refused now, not then
            writable(Path(config.out) / f"{_named('weights', name)}.npz")
            if config.local and config.learn:
                writable(Path(config.out) / f"{_named('experiences', name)}.npz")
        if config.behaviour_policy:
            handcoded = spec.handcoded(task) if spec.handcoded is not None else None
            controllers = Controllers(
                config.behaviour_policy, learners[0][1], np.array(first.action_low),
                np.array(first.action_high), handcoded, np.random.default_rng(config.seed + 7),
            )  # fmt: skip
        journals = [Path(config.out) / _named("journal", name) for name in behaviours.names]
        new_journals = [j for j in journals if not os.path.lexists(j)]
        for name, lcfg, learner, version in learners:  # each opens its journal, which checks its spec
            skills.append(Skill(name, lcfg, learner, make_brain(config, learner, name, version)))
        # Written once the rest is known to hold: a refused start leaves the last run's config as it was.
        write_json(Path(config.out) / "config.json", {"client": jsonable_config(config)})
    except BaseException as exc:
        try:
            _Brains(skills).stop()
        except BaseException as stop_exc:  # the refusal is what to report
            log_failure(log, "stopping the brains made before the refusal failed", stop_exc)
        for journal in new_journals:  # a refused start leaves no journal (and client id) of its making
            with contextlib.suppress(OSError):
                remove_empty_log(journal, also=(CLIENT_JSON,))
        if isinstance(exc, ValueError):  # options that do not fit this task or run directory
            raise SetupError(str(exc)) from exc
        raise
    brains = _Brains(skills)
    frames = FrameWriter(Path(config.out) / "cameras") if config.camera_every else None
    if frames is not None:  # C/S: the pictures also go to the servers' dashboards
        frames.on_png = getattr(skills[0].brain, "publish_view", None)
    for sk in skills:
        log.info("learner%s: %s (spec %s)", f" {sk.name}" if sk.name else "", sk.lcfg.short_repr(),
                 sk.lcfg.spec_hash())  # fmt: skip
    scores: list[float] = []
    rewards: deque[float] = deque(maxlen=RECENT)
    values: deque[float] = deque(maxlen=RECENT)
    learned = lockstep_timeouts = metric_not_finite = 0
    reward_squares, reward_count = 0.0, 0  # the first REWARD_ADVICE_AFTER finite rewards' (advice)
    # Values learnt normalised (deep.popart_rate) do not depend on the reward's scale.
    advise = config.learn and any(sk.lcfg.learner == "deep" and not sk.lcfg.deep.popart_rate for sk in skills)
    driven = np.zeros(len(skills), dtype=np.int64)
    """Ticks each behaviour drove."""
    outages: list[dict[str, float]] = []
    """Windows without a healthy weights source after the first one (unix times)."""
    outage_late = TickStats()  # lateness of the ticks during outages, in bounded memory
    startup_ticks = 0
    """Ticks before the first weights arrived."""
    produced: list[int] = []
    """With `timing_trace`: the last experience sent on by each tick's end (C/S; -1 otherwise)."""
    episode_policies: list[str] = []
    """The behaviour policy that drove each episode."""
    # A veto's proposal is learned only where its reward can be computed (Eq 5.4).
    twice = (several is not None or reward_of is not None) and config.safety.learn_twice

    def to_brain(sk: Skill, flags: int, acted: Acted | None) -> Learn:
        """A skill's learning in `robot_step`: each learnable experience, flagged, to its brain."""

        def learn(x: Any, u: Any, x_next: Any, reward: Any, terminal: Any, valid: Any) -> None:
            nonlocal learned
            if valid[0]:
                sk.brain.learn(Experience(x[0], u[0], x_next[0], float(reward[0]), bool(terminal[0]), flags),
                               acted)  # fmt: skip
                learned += 1

        return learn

    task.reset(rng)
    next_status = 0.0
    brains.start()
    start = time.perf_counter()

    robot_failed = False  # the robot (the task) failed: the learner is whole, saved as at an interrupt

    def robot(call: Callable[..., _R], *args: Any) -> _R:
        """`call(*args)`, a call of the robot (the task, its rewards and veto, the safety layer)."""
        nonlocal robot_failed
        try:
            return call(*args)
        except Exception:
            robot_failed = True
            raise

    def out_of_time(due: float) -> bool:
        """Whether a tick due then would start after the run's duration.

        At a slow rate, waiting for it overran the duration by up to a period (1,000 s at 0.001 Hz).
        """
        return config.duration_s is not None and due - start >= config.duration_s

    try:
        if config.lockstep and not brains.sync(config.lockstep_timeout_s):  # lock-step acts on weights only
            why = "; ".join(w for sk in skills if (w := getattr(sk.brain, "why_no_weights", lambda: "")()))
            raise TimeoutError(f"no weights from {', '.join(config.server)} in {config.lockstep_timeout_s} s"
                               + (f" ({why})" if why else ""))  # fmt: skip
        start = time.perf_counter()
        for episode in range(config.episodes):
            robot(spec.new_episode, task, rng)
            policy = controllers.choose() if controllers is not None else LEARNER
            episode_policies.append(controllers.recorded[policy] if controllers is not None else policy)
            total, steps, measured_steps = 0.0, 0, 0
            for _ in range(episode_steps):
                if steps and out_of_time(ticker.next_due()):  # not a wait for a tick past the duration
                    break
                late = ticker.wait()
                d = int(robot(behaviours.driving)[0])
                driver = skills[d].brain
                driven[d] += 1
                if driver.connected:
                    if outages and "end_unix" not in outages[-1]:
                        outages[-1]["end_unix"] = time.time()
                elif driver.following == "":
                    startup_ticks += 1
                else:
                    outage_late.add_lateness(late, 0.0)
                    if not outages or "end_unix" in outages[-1]:
                        outages.append({"start_unix": time.time()})
                t0 = time.perf_counter()
                xs = [robot(behaviours.observe, sk.name)[0] for sk in skills]
                if policy == LEARNER:
                    acted = driver.act(xs[d], explore=config.learn)
                else:  # another controller drives; the learner learns from its actions
                    assert controllers is not None
                    # The task's own controller is the robot's code; random and saved ones are not.
                    acted = (robot(controllers.act, policy, xs[d]) if policy == "handcoded"
                             else controllers.act(policy, xs[d]))  # fmt: skip
                proposed = acted.result.action if acted is not None else None
                decision = robot(safety.decide, proposed, xs[d], ticker.late_now() if period else 0.0)
                ticks.add_latency(time.perf_counter() - t0)
                vetoed = decision.proposed is not None
                proposal = decision.proposed if decision.proposed is not None else decision.executed
                decided = Decided(decision.executed[None], proposal[None], np.array([vetoed]))
                # Every behaviour learns from the executed action, whichever chose it (Section 6.6);
                # the driver also learns a vetoed proposal (learning twice).
                # The safe action was no one's choice: recorded as such ("", version 0), never
                # as the learner's (nor flagged explored by what its proposal had been).
                chose = None if decision.flags & EXP_SAFE_ACTION else acted
                # The other behaviours record who chose: the driving behaviour's learner by its
                # name (its weights are not theirs), another controller by its own.
                watched = (chose._replace(source=f"behaviour:{skills[d].name}")
                           if chose is not None and policy == LEARNER else chose)  # fmt: skip
                pupils = [
                    Pupil(xs[k][None], to_brain(sk, decision.flags, chose if k == d else watched), sk.name,
                          partial(robot, behaviours.reward, sk.name) if k == d and twice else None,
                          learn_proposal=to_brain(sk, EXP_VETO_PROPOSED, acted))
                    for k, sk in enumerate(skills)
                ] if config.learn else []  # fmt: skip
                transitions = robot_step(decided, partial(robot, behaviours.step), pupils)
                if not config.learn:  # the rewards still size what act judges diverged (learn would)
                    for sk in skills:
                        sk.learner.rewarded(transitions[sk.name].reward)
                if config.lockstep and config.learn and not brains.sync(config.lockstep_timeout_s):
                    lockstep_timeouts += 1
                    log.warning("lock-step: no snapshot covering experience %d in %.0f s",
                                learned, config.lockstep_timeout_s)  # fmt: skip
                measured = float(robot(spec.metric, task)[0])
                if np.isfinite(total + measured):
                    total += measured
                    measured_steps += 1
                else:  # a NaN reward, or finite ones summing past float64's range, would make the
                    metric_not_finite += 1  # whole episode's score NaN or infinite: counted apart
                reward = float(transitions[skills[d].name].reward[0])
                if math.isfinite(reward):  # a NaN one is never learned either
                    rewards.append(reward)
                    if advise and reward_count < REWARD_ADVICE_AFTER:
                        reward_squares, reward_count = reward_squares + reward * reward, reward_count + 1
                        if reward_count == REWARD_ADVICE_AFTER:
                            _advise_on_reward_scale(math.sqrt(reward_squares / reward_count), reward_count)
                if acted is not None and policy == LEARNER:
                    values.append(float(acted.result.value))
                if frames is not None and spec.views is not None and tick_count % config.camera_every == 0:
                    frames = _save_views(frames, tick_count, spec, task)
                if config.timing_trace:
                    produced.append(int(getattr(skills[0].brain, "produced_through", -1)))
                tick_count += 1
                steps += 1
                now = time.perf_counter()
                if now >= next_status:
                    brains.check()
                    fields = _status(brains, ticks, safety, rewards, values, episode, scores, now - start)
                    brains.report(fields)
                    if on_status is not None:
                        on_status(fields)
                    next_status = now + 0.5
                if config.duration_s is not None and now - start >= config.duration_s:
                    break
            # The mean over the steps whose metric was finite; NaN (null in the JSON) where none was.
            scores.append(total / measured_steps if measured_steps else float("nan"))
            if on_status is not None:
                on_status(_status(brains, ticks, safety, rewards, values, episode + 1, scores,
                                  time.perf_counter() - start))  # fmt: skip
            if out_of_time(ticker.next_due()):
                break
        wall = time.perf_counter() - start
    except BaseException as ended:
        try:
            _stop_brains(brains)  # what was recorded before the failure is kept
        except Exception as exc:  # the failure that ended the run is what to report
            log_failure(log, "stopping the brains after the run failed failed too", exc)
        if frames is not None:
            frames.close()
        interrupt = interrupt_behind(ended)  # raised in a compiled act, it came back as another error
        ended_outside = interrupt is not None or robot_failed
        if ended_outside and config.local and config.learn and _learners_whole(brains):
            # Ctrl-C or SIGTERM is how a long run is ended, and a robot (a simulation going
            # unstable, a task's own error) can fail in a step, before anything learned from it:
            # what the learner learned is kept (the journal keeps the experiences), so that
            # --weights resumes it. The learner's own failure is not trusted to have left it
            # whole, and its experiences can be learned again from the journal.
            why = "interrupted" if interrupt is not None else "the robot failed"
            try:
                saved = _save_weights(skills, config, len(scores))
            except Exception as exc:  # what ended the run is what to report, whatever the save met
                log_failure(log, f"saving the learner after the run ended ({why}) failed", exc)
            else:
                if saved:
                    log.warning("%s: %s saved in %s", why, ", ".join(saved), config.out)
        if interrupt is not None and interrupt is not ended:
            raise interrupt from None  # how the run ended (exit 130, or the signal's), not its wrapper
        raise
    noted = _stop_brains(brains)
    camera_frames = frames.close() if frames is not None else None
    raise_noted(noted)
    _finish_thinking(brains)
    brains.check()
    final = _status(brains, ticks, safety, rewards, values, len(scores), scores, wall, whole_run=True)
    out = Path(config.out)
    weights_saved = _save_weights(skills, config, len(scores))
    for sk in skills:
        if config.local and config.learn:
            save_experiences(
                out / f"{_named('experiences', sk.name)}.npz", sk.lcfg, sk.learner.buffer.contents(0)
            )
    config_record: dict[str, Any] = {"client": jsonable_config(config), "learner": skills[0].lcfg.to_dict()}
    learned_with = {server: json.loads(text) for sk in skills
                    for server, text in getattr(sk.brain, "learned_with", {}).items()}  # fmt: skip
    if learned_with:  # what the servers whose snapshots drove the robot actually learned with
        config_record["learned_with"] = learned_with
    metrics: dict[str, Any] = {
        "sim": config.sim,
        "metric": spec.metric_name(task) if callable(spec.metric_name) else spec.metric_name,
        "scores": scores,
        "episode_policies": episode_policies[: len(scores)],
        "first10_median": _median(scores[:10]),
        "last10_median": _median(scores[-10:]),
        "experiences_learned": learned,
        "lockstep_timeouts": lockstep_timeouts,
        "metric_not_finite": metric_not_finite,
        "wall_s": wall,
        "ticks": ticks.count,
        "safety": dict(safety.counts),
        "following": brains.following,
        "failovers": [f for sk in skills for f in getattr(sk.brain, "failovers", [])],
        "outages": outages,
        "client/tick_jitter_ms_p99_outage": (
            outage_late.summary()["tick_jitter_ms_p99"] if outage_late.ticks else None
        ),
        "client/outage_ticks": outage_late.ticks,
        "client/startup_ticks": startup_ticks,
        "config": config_record,
        "camera_frames": camera_frames,
        "weights_saved": weights_saved,
        **final,
    }
    returns = getattr(task, "returns", None)
    if returns is not None:  # the task's own episodes (a Gymnasium task's), not the client's
        task_returns = [float(r) for r in returns]
        metrics.update(task_episodes=len(task_returns), task_returns=task_returns,
                       task_returns_last10_median=_median(task_returns[-10:]))  # fmt: skip
    if several is not None:
        metrics["behaviours"] = {
            sk.name: {"learner": sk.lcfg.to_dict(), "ticks_driving": int(driven[k])}
            for k, sk in enumerate(skills)
        }
        forage = getattr(several, "forage", None)
        if forage is not None:
            metrics["targets_found"], metrics["targets_reached"] = (
                int(forage.found[0]),
                int(forage.reached[0]),
            )
    if config.timing_trace:
        metrics["trace"] = {
            "tick_lateness_ms": [v * 1e3 for v in ticks.lateness_s],
            "act_latency_ms": [v * 1e3 for v in ticks.latency_s],
            "snapshot_latency_ms": [v for sk in skills for v in getattr(sk.brain, "apply_latency_ms", [])],
            "tick_due_unix": ticks.due_unix,
            "tick_produced_through": produced,
            "snapshots_applied": [list(a) for sk in skills for a in getattr(sk.brain, "applied", [])],
        }
    write_json(out / "metrics.json", metrics)
    if config.json_stats is not None:
        write_json(config.json_stats, metrics)
    curve = out / "learning_curve.png"
    try:
        plot(metrics, curve)
    except (ValueError, OverflowError) as exc:  # scores near float64's largest: matplotlib cannot scale them
        curve.unlink(missing_ok=True)  # an earlier run's in this folder is not this run's curve
        log.warning("%s not drawn (%s); the scores are in metrics.json", curve, exc)
    return metrics


THINKING_GRACE_S = 300.0
"""How long a run that ended waits for a think thread still in its update before giving up."""


def _finish_thinking(brains: _Brains) -> None:
    """At a run's normal end, wait for a think thread that outlived its stop's wait.

    Saved meanwhile, the learner would be whatever half of an update the thread had made. One
    that does not finish within THINKING_GRACE_S is not saved: the run ends on an error instead.
    """
    grace_s = THINKING_GRACE_S
    for sk in brains.skills:
        if isinstance(sk.brain, LocalBrain) and sk.brain.thinking:
            log.warning("%s still thinking at the run's end: waiting up to %.0f s for its update",
                        sk.name or "the learner", grace_s)  # fmt: skip
            if not sk.brain.finish_thinking(grace_s):
                raise RuntimeError(f"{sk.name or 'the learner'} still thinking {grace_s:g} s after the "
                                   "run ended: not saved (the journal keeps its experiences)")  # fmt: skip


def _learners_whole(brains: _Brains) -> bool:
    """Whether the local learners are whole, to be saved with no half-made update.

    None failed, and none still thinks (its think thread outlived its stop's wait).
    """
    try:
        brains.check()
    except Exception as exc:
        log_failure(log, "the learner is not saved: it failed too", exc)
        return False
    thinking = [sk.name or "the learner" for sk in brains.skills if getattr(sk.brain, "thinking", False)]
    if thinking:
        log.error("%s not saved: still thinking when the run ended", ", ".join(thinking))
    return not thinking


def _given_weights(config: ClientConfig, name: str) -> Path | None:
    """Behaviour `name`'s weights file given by `--weights`, if any."""
    if config.weights is None:
        return None
    return config.weights if not name else config.weights / f"{_named('weights', name)}.npz"


def _refuse_a_learning_runs_folder(out: Path) -> None:
    """Refuse, for a run that learns nothing, the folder of a run that learned.

    Its outputs would replace that run's config.json, metrics.json and learning curve, and its
    weights without the training state saved beside them (a `--no-learn --weights RUN/weights.npz
    --out RUN` evaluation). A config.json that cannot be read is taken for a run that learned.
    """
    path = out / "config.json"
    if not os.path.lexists(path):
        return
    try:
        learned = json.loads(read_regular_text(path))["client"]["learn"] is not False
    except (OSError, ValueError, KeyError, TypeError):
        learned = True
    if learned:
        raise ValueError(
            f"--no-learn: {out} holds the outputs of a run that learned (its config.json), which this "
            "run's would replace: give another --out"
        )


def _save_weights(skills: list[Skill], config: ClientConfig, episodes: int) -> list[str]:
    """Save each behaviour's weights in the run directory -> the files written.

    With the training state of a learner that learned here. The file given by `--weights` is
    replaced only by a learner that learned from it here: other weights (a server's, or the same
    ones without the training state saved beside them) would lose what it holds.
    """
    saved: list[str] = []
    for sk in skills:
        current = getattr(sk.brain, "current", None)  # C/S: the snapshot act used last
        params = sk.learner.params if config.local else (current.params if current is not None else None)
        meta: dict[str, Any] = {"sim": config.sim, "task": config.task, "episodes": episodes,
                                "following": sk.brain.following,
                                "behaviour": sk.name}  # fmt: skip
        # Resumed with --weights (learning or not), the count and version go on; weights given
        # without them are not said to have thought none.
        counted = getattr(sk.brain, "version", None)
        if config.local and (config.learn or counted):
            meta["thinks"] = int(sk.learner.thinks[0])
            meta["version"] = int(counted or 0)
        name = f"{_named('weights', sk.name)}.npz"
        given, path = _given_weights(config, sk.name), Path(config.out) / name
        if not (config.local and config.learn) and given is not None and _same_file(given, path):
            log.info("%s is the file this run was given (--weights): kept as it was", path)
            continue
        try:
            if params is not None:
                # A learner that learned here keeps its training state beside the weights (a think
                # server's is in its own checkpoints), so that --weights resumes it whole.
                training = sk.learner.training_state() if config.local and config.learn else None
                save_weights(path, sk.lcfg, params, meta, training=training)
                saved.append(name)
        except PersistError as exc:  # weights diverged past what the monitor reset (the run ended first)
            log.error("%s at the end of the run", exc)
    return saved


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them is not there (or cannot be looked at): not the same file
        return False


class _Brains:
    """The behaviours' brains handled together (one brain: exactly that brain)."""

    def __init__(self, skills: list[Skill]) -> None:
        self.skills = skills

    @property
    def following(self) -> str:
        """Whose weights act uses; with several behaviours "servo:srv1 wander:srv2"."""
        if len(self.skills) == 1:
            return self.skills[0].brain.following
        return " ".join(f"{sk.name}:{sk.brain.following or '-'}" for sk in self.skills)

    def start(self) -> None:
        for sk in self.skills:
            sk.brain.start()

    def stop(self) -> None:
        """Stop every brain (each keeps its record), then raise the first error any raised."""
        first: BaseException | None = None
        for sk in self.skills:
            try:
                sk.brain.stop()
            except BaseException as exc:  # the others' records must still be closed
                first = first or exc
        if first is not None:
            raise first

    def sync(self, timeout_s: float) -> bool:
        return all(sk.brain.sync(timeout_s) for sk in self.skills)

    def check(self) -> None:
        for sk in self.skills:
            sk.brain.check()

    def report(self, fields: dict[str, Any]) -> None:
        for sk in self.skills:
            sk.brain.report(fields)

    def metrics(self) -> dict[str, float]:
        """The brain's figures (several: each under `<behaviour>/`)."""
        if len(self.skills) == 1:
            return self.skills[0].brain.metrics()
        each = {sk.name: sk.brain.metrics() for sk in self.skills}
        totals = {k: sum(m.get(k, 0.0) for m in each.values()) for k in TOTALS}
        return {**totals, **{f"{name}/{k}": v for name, m in each.items() for k, v in m.items()}}


TOTALS = ("think/thinks", "learn/experiences", "learn/divergence_resets", "learn/rejected")
"""Brain figures that add up over several behaviours' brains."""


def _save_views(frames: FrameWriter, tick: int, spec: SimSpec, task: VecTask) -> FrameWriter | None:
    """Hand this tick's camera views to the writer; stop saving (None) where nothing can render."""
    assert spec.views is not None
    try:
        frames.submit(tick, spec.views(task))
    except RuntimeError as exc:  # no GL here: the run goes on without pictures
        log.warning("camera frames off: %s", exc)
        frames.close()
        return None
    return frames


RECENT = 1000
"""Ticks the live status summarises (the whole run only at the end: no growing work per tick)."""


def _advise_on_reward_scale(rms: float, n: int) -> None:
    """Tell a deep learner's run whose rewards lie far outside the scale its defaults suit."""
    low, high = SUITED_REWARD_RMS
    if not low <= rms <= high:  # inf (squares past float64's range) too
        log.warning("the first %d rewards' root-mean-square is %.3g a step, outside %g-%g: the deep "
                    "learner's defaults (Adam's step, the separation weight) do not suit rewards of that "
                    "scale and it may learn nothing (README: a limitation: the reward's scale); learn "
                    "normalised values (--learner-options '{\"deep\": {\"popart_rate\": 0.0003}}') or "
                    "scale the task's rewards", n, rms, low, high)  # fmt: skip


def _median(scores: list[float]) -> float:
    """The median of the finite scores (NaN where there are none)."""
    finite = [v for v in scores if math.isfinite(v)]
    return float(np.median(finite)) if finite else float("nan")


def _status(
    brain: _Brains, ticks: TickStats, safety: SafetyLayer, rewards: deque[float], values: deque[float],
    episode: int, scores: list[float], elapsed: float, whole_run: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Figures of the run; tick timing over the last RECENT ticks, or all with `whole_run`."""
    return {
        "episode": episode,
        "client/score": scores[-1] if scores else float("nan"),
        "elapsed_s": elapsed,
        "following": brain.following,
        "client/reward_mean": float(np.mean(rewards)) if rewards else float("nan"),
        "client/q_mean": float(np.mean(values)) if values else float("nan"),
        "client/safe_actions": float(sum(safety.counts[k] for k in ("no_weights", "late", "non_finite"))),
        "client/vetoes": float(safety.counts["vetoed"]),
        **ticks.summary("client/", None if whole_run else RECENT),
        **brain.metrics(),
    }


def jsonable_config(config: ClientConfig) -> dict[str, Any]:
    """The whole client config as plain JSON values."""
    return dict(to_jsonable(dataclasses.asdict(config)))


def plot(metrics: dict[str, Any], path: Path) -> None:
    """Score per episode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    scores = metrics["scores"]
    ax.plot(np.arange(1, len(scores) + 1), scores, marker="o", ms=3)
    ax.set_xlabel("episode")
    ax.set_ylabel(metrics["metric"])
    where = "in-process" if metrics["following"] == "local" else f"server {metrics['following'] or '-'}"
    ax.set_title(f"{metrics['sim']}: {metrics['experiences_learned']} experiences, thinking {where}")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
