"""Any Gymnasium task with 1-D Box observations and actions, as a task the client can drive.

`GymVec(env_id)` wraps one environment (n = 1) behind the `sims.base.VecTask` interface:
states are observations, actions are clipped to the action space, and an episode that ends
(terminated or truncated) is restarted inside `step`, so `observe` is always the state to act
from. The transition into the end is learned: as a terminal one when the task terminated (no
value after it), as an ordinary one when only the time limit truncated it.

Declared ranges (the learner scales states and actions by them) come from the spaces. Where an
observation bound is infinite (most MuJoCo tasks), its range is measured instead: the 1st and
99th percentiles of the observations met over `probe_steps` random actions, widened by half
their span on each side (on the task itself, before the run: ranges measured before, given as
`state_ranges`, are taken instead). Such ranges are estimates from a random policy, which rarely goes
where a good one does (a balanced pole's cart drifts far beyond where random pushes ever
took it), so the task then declares `valid_margin` = MEASURED_MARGIN: the learner's sanity
limits refuse only non-finite observations, not those beyond an estimated range. A bound of at
least `UNBOUNDED` in size counts as infinite (Gymnasium tasks often write "no bound" as float32's
largest number); an observation the probe never saw move (it stayed within `STILL`) gets a range
of 1 around its value, since the probe cannot tell its scale; the probe's non-finite values are
left out.
"""

from __future__ import annotations

import logging
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from sims.base import Transition
from wfnn_common.config import MAX_ACTION_DIM, MAX_STATE_DIM

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
MEASURED_MARGIN = 1e6
"""The sanity margin of a task whose ranges were measured: only non-finite states are refused."""
UNBOUNDED = 1e10
"""A space's bound at least this large stands for no bound."""
STILL = 1e-3
"""A measured observation whose 1st-99th percentile span is below this did not move in the probe."""
PROBE_SEED = 12345
"""The seed of the probe that measures unbounded observations' ranges. Not the run's: the ranges
go into the learner's spec, so runs of one task with other seeds share weights, logs and servers."""


def make_env(env_id: str, **make_kwargs: Any) -> gym.Env[Any, Any]:
    """`gym.make(env_id)`, checked: 1-D Box spaces, actions real, bounded, with high > low.

    Anything else is refused with a ValueError that says why.
    """
    try:
        env = gym.make(env_id, **make_kwargs)
    except gym.error.Error as exc:  # the cause is in the message: not chained, so not told twice
        raise ValueError(f"Gymnasium cannot make {env_id!r}: {exc}") from None
    except ImportError as exc:  # a missing package, or one gymnasium asks for by message
        raise ValueError(f"{env_id!r} needs a package that is not installed: {exc}") from None
    except Exception as exc:  # the task's own constructor failed: still one line, naming the task
        raise ValueError(f"Gymnasium cannot make {env_id!r}: {type(exc).__name__}: {exc}") from None
    problem = _space_problem(env)
    if problem:
        env.close()
        raise ValueError(f"{env_id}: {problem}")
    return env


def control_rate(env: gym.Env[Any, Any]) -> float:
    """The task's own control rate in Hz: 1 / its time step `dt`, where it declares one, else 50."""
    dt = getattr(env.unwrapped, "dt", None)
    try:
        rate = 1.0 / float(dt) if dt else 50.0
    except (TypeError, ValueError):
        return 50.0
    return rate if np.isfinite(rate) and rate > 0 else 50.0


def _space_problem(env: gym.Env[Any, Any]) -> str:
    """Why the task's spaces cannot be learned here, or ""."""
    for what, space, most in (("observation", env.observation_space, MAX_STATE_DIM),
                              ("action", env.action_space, MAX_ACTION_DIM)):  # fmt: skip
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            return f"the {what} space must be a 1-D Box, got {space}"
        if space.shape[0] > most:  # before a probe of its ranges, whose memory grows with it
            return f"at most {most} {what} variables, got {space.shape[0]}"
    act = env.action_space
    assert isinstance(act, gym.spaces.Box)
    if not np.issubdtype(act.dtype, np.floating):  # whole numbers would truncate the actions learned
        return f"the action space must hold real numbers, got {act}"
    low, high = act.low.astype(np.float64), act.high.astype(np.float64)
    if not ((np.abs(low) < UNBOUNDED) & (np.abs(high) < UNBOUNDED)).all():
        return f"the action space must be bounded (each bound below {UNBOUNDED:g} in size), got {act}"
    fixed = np.flatnonzero(~(high > low))
    if fixed.size:
        return f"action {int(fixed[0])} has low = high = {low[fixed[0]]:g}: a fixed action cannot be learned"
    return ""


NOT_NUMBERS = (str, bytes, complex, np.str_, np.bytes_, np.complexfloating)
"""Text and bytes, which float() parses, and complex numbers, whose real part numpy's float()
takes with only a warning: not a reward, nor part of an observation."""


def _shape_of(value: Any) -> str:
    """What a value is, in a few words, for an error message."""
    if isinstance(value, tuple):
        return f"a tuple of {len(value)}"
    return f"a {type(value).__name__}"


class GymVec:
    """One Gymnasium environment as a vectorised task of one instance."""

    n = 1

    def __init__(
        self, env_id: str, seed: int = 0, probe_steps: int = 2000,
        state_ranges: tuple[tuple[float, ...], tuple[float, ...]] | None = None,
        ranges_from: str = "the ranges given", **make_kwargs: Any,
    ) -> None:  # fmt: skip
        """One environment of `env_id`, its ranges declared or measured (module docstring).

        `state_ranges` (low, high), where given, are the ranges as measured before (saved with
        weights), so that no random action is sent to measure them (ValueError: they are not of
        the observations' size; `ranges_from` names where they came from).
        """
        self.env = make_env(env_id, **make_kwargs)
        obs, act = self.env.observation_space, self.env.action_space
        assert isinstance(obs, gym.spaces.Box) and isinstance(act, gym.spaces.Box)
        self.env_id = env_id
        self.seed = seed
        self.action_low = tuple(float(v) for v in act.low)
        self.action_high = tuple(float(v) for v in act.high)
        low, high = obs.low.astype(np.float64), obs.high.astype(np.float64)
        low[~(np.abs(low) < UNBOUNDED)], high[~(np.abs(high) < UNBOUNDED)] = -np.inf, np.inf
        self.valid_margin = 1.0
        """How far outside its ranges (in range widths) a state is still learned (`LearnerConfig`)."""
        bounded = bool(np.isfinite(low).all() and np.isfinite(high).all())
        if state_ranges is not None and not bounded:
            if not len(state_ranges[0]) == len(state_ranges[1]) == len(low):  # not measured on this task
                self.env.close()
                raise ValueError(f"{ranges_from}: ranges for {len(state_ranges[0])} observations, {env_id} "
                                 f"has {len(low)} (another task's?)")  # fmt: skip
            saved = [np.array(r, dtype=np.float64) for r in state_ranges]
            low, high = np.where(np.isfinite(low), low, saved[0]), np.where(np.isfinite(high), high, saved[1])
            self.valid_margin = MEASURED_MARGIN
        elif not bounded:
            declared, unbounded = (obs.low, obs.high), ~(np.isfinite(low) & np.isfinite(high))
            with np.errstate(over="ignore", invalid="ignore"):  # told below, naming the observation
                low, high, seen = self._measured_ranges(low, high, probe_steps)
            self.valid_margin = MEASURED_MARGIN
            unseen = np.flatnonzero(unbounded & ~seen)
            if unseen.size:  # what its measured range would be is made up, not measured
                i = int(unseen[0])
                raise ValueError(f"{env_id}: observation {i} is declared in [{declared[0][i]:g}, "
                                 f"{declared[1][i]:g}] and was never finite under random actions: its "
                                 "range cannot be measured")  # fmt: skip
            wrong = np.flatnonzero(~(np.isfinite(low) & np.isfinite(high) & (high >= low)))
            if wrong.size:  # one bound declared, the other measured beyond it; or values too large
                i = int(wrong[0])
                raise ValueError(
                    f"{env_id}: observation {i} is declared in [{declared[0][i]:g}, {declared[1][i]:g}]; "
                    f"with its unbounded side measured under random actions it spans [{low[i]:g}, "
                    f"{high[i]:g}]: the task's observations lie beyond its declared bound, or are too "
                    "large to scale"
                )
        constant = ~(high > low)  # declared so: an observation that never changes (range 1 around it,
        half = np.maximum(0.5, 0.5e-6 * np.abs(low))  # or wider far from 0, as for a still one above)
        low, high = np.where(constant, low - half, low), np.where(constant, high + half, high)
        self.state_low = tuple(float(v) for v in low)
        self.state_high = tuple(float(v) for v in high)
        self.state_names = tuple(f"obs_{i}" for i in range(len(low)))
        spec = self.env.spec
        self.max_episode_steps = int(spec.max_episode_steps) if spec and spec.max_episode_steps else 1000
        self.rate_hz = control_rate(self.env)
        """The task's own control rate (1 / its time step, where it declares one)."""
        self.max_reward: float | None = getattr(self.env.unwrapped, "max_reward", None)
        """The largest reward where the task declares it (this project's own do); else None, unknown,
        as for Gymnasium's tasks (`LearnerConfig.for_task`)."""
        self._obs = np.zeros((1, len(low)))
        self._failed: Exception | None = None
        """The restart at an episode's end that failed: raised by the next `observe` or `step`, once
        the transition into the end (which happened) has been returned, to be learned and recorded."""
        self.last_reward = np.zeros(1)
        self.episode_return = 0.0
        self.returns: list[float] = []
        """Returns of the episodes finished so far (the task's own score)."""
        self.episodes = 0

    def _measured_ranges(
        self, low: FloatArray, high: FloatArray, steps: int
    ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """(low [S], high [S], seen [S]): declared bounds, measured where infinite; seen where finite."""
        rng = np.random.default_rng(PROBE_SEED)
        seen = []
        obs = self._reset(PROBE_SEED)
        self.env.action_space.seed(PROBE_SEED)  # unseeded, the ranges would differ per run
        for _ in range(steps):
            seen.append(self._observation(obs)[0])
            sample = self.env.action_space.sample()
            obs, _, terminated, truncated = self._step(sample)
            if terminated or truncated:
                obs = self._reset(int(rng.integers(2**31)))
        data = np.asarray(seen, dtype=np.float64)
        data[~np.isfinite(data)] = np.nan  # a NaN or infinite observation says nothing of the range
        finite = np.asarray(~np.isnan(data).all(axis=0), dtype=np.bool_)  # any finite value in the probe
        p1, p99 = np.zeros(data.shape[1]), np.zeros(data.shape[1])
        if finite.any():
            p1[finite], p99[finite] = np.nanpercentile(data[:, finite], [1, 99], axis=0)
        # A still one gets a width of 1, or more beyond 1e6: scaling needs a width that float64
        # resolves at its value (`LearnerConfig`'s MIN_HALF_RANGE).
        span = np.where(p99 - p1 < STILL, np.maximum(1.0, 1e-6 * np.abs(0.5 * (p1 + p99))), p99 - p1)
        measured_low, measured_high = p1 - 0.5 * span, p99 + 0.5 * span
        return (
            np.where(np.isfinite(low), low, measured_low),
            np.where(np.isfinite(high), high, measured_high),
            finite,
        )

    def _observation(self, obs: Any) -> FloatArray:
        """The env's observation as states [1, S].

        ValueError naming the task where it does not fit its space: a learner given it would fail
        later, naming the learner, the record or the log.
        """
        shape = self.env.observation_space.shape
        try:
            raw = np.asarray(obs)
            # Complex numbers (whose real part alone float64 would keep), text (which it would
            # parse) and dates are not observations, in an array of objects too.
            objects = raw.dtype.kind == "O"
            if raw.dtype.kind in "cUSVMm" or (objects and any(isinstance(v, NOT_NUMBERS) for v in raw.flat)):
                raise ValueError(f"of dtype {raw.dtype}")
            x = raw.astype(np.float64, copy=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.env_id} returned an observation that is not numbers ({exc})") from None
        if x.shape != shape:
            raise ValueError(f"{self.env_id} returned an observation of shape {x.shape}; its observation "
                             f"space has shape {shape}")  # fmt: skip
        return x[None]

    def _reward(self, reward: Any) -> float:
        """The env's reward as a float; ValueError naming the task where it is not one number.

        Gymnasium types a reward as anything `float()` takes (numpy's and Python's numbers, a
        0-d tensor, a Fraction); text, which float() would parse, and arrays of several numbers
        are not rewards.
        """
        try:
            shape = np.shape(reward)
        except Exception:
            shape = None
        value: float | None = None
        if shape == () and not isinstance(reward, NOT_NUMBERS):
            try:
                value = float(reward)
            except (TypeError, ValueError, OverflowError):
                value = None
        if value is None:
            shown = f"array of shape {shape}" if shape not in (None, ()) else repr(reward)[:60]
            raise ValueError(f"{self.env_id} returned a reward that is not one number: {shown}")
        return value

    def _task(self, what: str, call: Any, *args: Any, **kwargs: Any) -> Any:
        """`call(...)` of the env; its own failure as one line naming the task (the cause chained)."""
        try:
            return call(*args, **kwargs)
        except Exception as exc:
            raise RuntimeError(f"{self.env_id} failed in {what}: {type(exc).__name__}: {exc}") from exc

    def _reset(self, seed: int | None) -> Any:
        """The env's reset -> its observation.

        ValueError naming the task where it does not return Gymnasium's (observation, info).
        """
        out = self._task("reset", self.env.reset, seed=seed)
        if not (isinstance(out, tuple) and len(out) == 2):
            raise ValueError(f"{self.env_id}: reset() returned {_shape_of(out)}, not Gymnasium's "
                             "(observation, info)")  # fmt: skip
        return out[0]

    def _step(self, action: Any) -> tuple[Any, Any, bool, bool]:
        """The env's step -> (observation, reward, terminated, truncated).

        ValueError naming the task where it does not return Gymnasium's five (an old API's four).
        """
        out = self._task("step", self.env.step, action)
        if not (isinstance(out, tuple) and len(out) == 5):
            raise ValueError(f"{self.env_id}: step() returned {_shape_of(out)}, not Gymnasium's "
                             "(observation, reward, terminated, truncated, info)")  # fmt: skip
        return out[0], out[1], bool(out[2]), bool(out[3])

    def reset(self, rng: np.random.Generator) -> FloatArray:
        """A new episode -> states [1, S]."""
        obs = self._reset(int(rng.integers(2**31)))
        self._obs = self._observation(obs)
        if self._failed is not None:  # told: no call raised it, and the task is whole again
            log.warning("%s: a restart at an episode's end failed (%s); the reset after it worked",
                        self.env_id, self._failed)  # fmt: skip
        self._failed = None
        self.episode_return = 0.0
        return self.observe()

    def observe(self) -> FloatArray:
        """The observation to act from [1, S] (the error of a failed restart, where one failed)."""
        if self._failed is not None:
            raise self._failed
        return self._obs.copy()

    def step(self, action: FloatArray) -> Transition:
        """One environment step with actions [1, A]; a finished episode restarts at once."""
        if self._failed is not None:
            raise self._failed
        u = np.clip(np.asarray(action, dtype=np.float64).reshape(1, -1)[0], self.action_low, self.action_high)
        obs, reward, terminated, truncated = self._step(u.astype(self.env.action_space.dtype))
        next_state = self._observation(obs)
        r = self._reward(reward)
        self.last_reward = np.array([r])
        self.episode_return += r
        if terminated or truncated:
            self.returns.append(self.episode_return)
            self.episodes += 1
            self.episode_return = 0.0
            try:
                self._obs = self._observation(self._reset(None))
            except Exception as exc:  # raised at the next call: this transition happened, and is kept
                self._failed = exc
        else:
            self._obs = next_state.copy()
        return Transition(
            next_state, self.last_reward.copy(), np.array([bool(terminated)]), np.ones(1, dtype=np.bool_)
        )

    def close(self) -> None:
        """Close the environment."""
        self.env.close()
