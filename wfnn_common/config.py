"""Typed configuration of the WFNN learner (one frozen dataclass per component)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from typing import Any, Literal

from wfnn_common.symmetry import Symmetry

ExplorationKind = Literal["none", "uniform", "gaussian", "smooth"]


class ConfigError(ValueError):
    """A configuration value is out of its allowed range or inconsistent."""


@dataclass(frozen=True, kw_only=True)
class ExplorationConfig:
    """How `act` perturbs the best wire's action (thesis Sections 3.4, 6.4.1, 6.7)."""

    kind: ExplorationKind = "uniform"
    """`uniform`: replace the action by a uniform random one with probability `p` (Section 3.4);
    `gaussian`: add N(0, sigma) noise, as on the robots; `smooth`: add smoothly varying noise
    (an Ornstein-Uhlenbeck process with time constant `tau_steps`); `none`: greedy."""
    p: float = 0.1
    """Probability of a uniform random action (kind `uniform`)."""
    sigma: float = 0.1
    """Noise standard deviation in scaled action units, where the declared range is [-1, 1]."""
    tau_steps: float = 10.0
    """Correlation time of the smooth noise, in actions."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.p <= 1.0:
            raise ConfigError(f"exploration.p must be in [0, 1], got {self.p}")
        if self.sigma < 0.0:
            raise ConfigError(f"exploration.sigma must be >= 0, got {self.sigma}")
        if self.tau_steps < 1.0:
            raise ConfigError(f"exploration.tau_steps must be >= 1, got {self.tau_steps}")


@dataclass(frozen=True, kw_only=True)
class LearnerConfig:
    """Everything that defines a WFNN learner. Defaults are the thesis' (Section 4.4)."""

    state_low: tuple[float, ...]
    """Lower end of each state variable's declared range (physical units); mapped to -1."""
    state_high: tuple[float, ...]
    """Upper end of each state variable's declared range; mapped to +1."""
    action_low: tuple[float, ...]
    """Lower end of each action variable's range; actions are always clipped into it."""
    action_high: tuple[float, ...]
    """Upper end of each action variable's range."""
    n_hidden: int = 10
    """Hidden tanh neurons."""
    n_wires: int = 9
    """Wires (action, value pairs) output by the network for each state."""
    gamma: float = 0.8
    """Discount factor."""
    advantage_k: float = 0.2
    """Advantage learning factor k of Eq 4.1; k = 1 is one-step Q-learning."""
    alpha: float = 0.25
    """Global learning rate; each layer uses alpha / sqrt(fan-in), bias included."""
    smoothing_c: float = 0.01
    """Wire fitter smoothing factor c of Eq 3.1."""
    eps: float = 1e-4
    """Wire fitter epsilon of Eq 3.1 (keeps every distance positive)."""
    derivatives: Literal["approx", "exact"] = "approx"
    """`approx`: Eq 3.4-3.5 as in the thesis (inexact for the top wire); `exact`: the full
    derivative including the top wire's effect on every distance."""
    thinks_per_action: int = 200
    """Experience replays per action."""
    update: Literal["incremental", "minibatch"] = "incremental"
    """`incremental`: one experience per weight update (the thesis' rule); `minibatch`: the
    mean gradient of `batch_size` experiences per update."""
    batch_size: int = 256
    """Experiences per update in minibatch mode."""
    minibatch_dtype: Literal["float32", "float64"] = "float32"
    """Arithmetic of minibatch updates (torch); float64 matches the numpy reference."""
    bc_weight: float = 0.0
    """Behaviour-cloning pull on the best wire (TD3+BC's idea, Fujimoto and Gu 2021, for
    wires): each replay also moves the best wire's action toward the experience's action by
    this fraction of their difference (in scaled units), beside the wire-fitting update. 0 is
    the thesis' learner. For passive learning (logs of other controllers, `--replay-only`):
    with no robot to try the greedy action, nothing corrects a wire over-valued at an action
    the data never took, and the greedy controller drives the robot out of the data;
    `wfnn-bench passive` measures it."""
    squash_reward: bool = True
    """Apply Eq 3.6, r = (1 - gamma) tanh(raw reward), before learning."""
    replay_capacity: int = 100_000
    """Experiences kept per learner; the oldest is overwritten when full."""
    valid_margin: float = 1.0
    """Sanity limit: a state further outside its declared range than this fraction of the
    range's width is invalid (acted on when clipped, never learned from)."""
    divergence_threshold: float = 0.5
    """Value of chosen actions above which the learner may have diverged (Section 7.6.2)."""
    divergence_patience: int = 50
    """Consecutive chosen actions above the threshold that count as divergence; 0 disables."""
    init_scale: float = 1.0
    """Initial weights are uniform in +-init_scale / sqrt(fan-in)."""
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    """Exploration strategy used by `act` when exploring."""
    seed: int = 0
    """Seed of the learner's random streams (weights, replay sampling, exploration)."""
    symmetries: tuple[Symmetry, ...] = ()
    """Declared symmetries of the task: each experience learned is also learned transformed
    by each of them (e.g. the boat's mirror image). The store and logs keep only the real
    experiences; the thinks owed per action are unchanged."""

    def __post_init__(self) -> None:
        s_lo, s_hi, a_lo, a_hi = self.state_low, self.state_high, self.action_low, self.action_high
        if len(s_lo) == 0 or len(s_lo) != len(s_hi):
            raise ConfigError(f"state_low/high must be non-empty and equal length, got {s_lo}, {s_hi}")
        if len(a_lo) == 0 or len(a_lo) != len(a_hi):
            raise ConfigError(f"action_low/high must be non-empty and equal length, got {a_lo}, {a_hi}")
        for name, lo, hi in (("state", s_lo, s_hi), ("action", a_lo, a_hi)):
            for i, (a, b) in enumerate(zip(lo, hi, strict=True)):
                if not (math.isfinite(a) and math.isfinite(b) and b > a):
                    raise ConfigError(f"{name} range {i} must be finite with high > low, got [{a}, {b}]")
        checks: list[tuple[bool, str]] = [
            (self.n_hidden >= 1, "n_hidden must be >= 1"),
            (self.n_wires >= 1, "n_wires must be >= 1"),
            (0.0 <= self.gamma < 1.0, "gamma must be in [0, 1)"),
            (0.0 < self.advantage_k <= 1.0, "advantage_k must be in (0, 1]"),
            (self.alpha > 0.0, "alpha must be > 0"),
            (self.smoothing_c >= 0.0, "smoothing_c must be >= 0"),
            (self.eps > 0.0, "eps must be > 0"),
            (math.isfinite(self.bc_weight) and self.bc_weight >= 0.0, "bc_weight must be finite and >= 0"),
            (self.thinks_per_action >= 0, "thinks_per_action must be >= 0"),
            (self.batch_size >= 1, "batch_size must be >= 1"),
            (self.replay_capacity >= 1, "replay_capacity must be >= 1"),
            (self.valid_margin >= 0.0, "valid_margin must be >= 0"),
            (self.divergence_patience >= 0, "divergence_patience must be >= 0"),
            (self.init_scale > 0.0, "init_scale must be > 0"),
            (self.derivatives in ("approx", "exact"), "derivatives must be 'approx' or 'exact'"),
            (self.update in ("incremental", "minibatch"), "update must be 'incremental' or 'minibatch'"),
            (self.minibatch_dtype in ("float32", "float64"), "minibatch_dtype must be float32 or float64"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"{message} (config: {self.short_repr()})")
        for symmetry in self.symmetries:
            try:
                symmetry.check_dims(self.state_dim, self.action_dim)
            except ValueError as exc:
                raise ConfigError(str(exc)) from exc

    @classmethod
    def for_task(cls, task: Any, **overrides: Any) -> LearnerConfig:
        """A config over a task's declared ranges, the thesis' defaults where not overridden.

        `task` is anything with state_low, state_high, action_low and action_high.
        """
        return cls(
            state_low=tuple(task.state_low), state_high=tuple(task.state_high),
            action_low=tuple(task.action_low), action_high=tuple(task.action_high), **overrides,
        )  # fmt: skip

    # ----------------------------------------------------------------- derived sizes
    @property
    def state_dim(self) -> int:
        """Number of state variables."""
        return len(self.state_low)

    @property
    def action_dim(self) -> int:
        """Number of action variables."""
        return len(self.action_low)

    @property
    def n_outputs(self) -> int:
        """Network outputs: n_wires actions of action_dim, then n_wires values."""
        return self.n_wires * (self.action_dim + 1)

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form of the config."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LearnerConfig:
        """Inverse of `to_dict`; unknown keys are an error."""
        data = dict(data)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"unknown LearnerConfig fields: {sorted(unknown)}")
        exploration = data.pop("exploration", None)
        for key in ("state_low", "state_high", "action_low", "action_high"):
            if key in data:
                data[key] = tuple(float(v) for v in data[key])
        if isinstance(exploration, dict):
            data["exploration"] = ExplorationConfig(**exploration)
        if "symmetries" in data:
            try:
                data["symmetries"] = tuple(
                    s if isinstance(s, Symmetry) else Symmetry.from_dict(s) for s in data["symmetries"]
                )
            except ValueError as exc:
                raise ConfigError(str(exc)) from exc
        return cls(**data)

    def to_json(self) -> str:
        """Canonical JSON (sorted keys), used for hashing and saving."""
        return json.dumps(self.to_dict(), sort_keys=True)

    def spec_hash(self) -> str:
        """Hash of the fields that fix the network's shape and the meaning of its inputs.

        Two learners with the same spec hash can exchange weights and experiences.
        """
        spec = {
            "state_low": self.state_low,
            "state_high": self.state_high,
            "action_low": self.action_low,
            "action_high": self.action_high,
            "n_hidden": self.n_hidden,
            "n_wires": self.n_wires,
        }
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]

    def short_repr(self) -> str:
        """One line for logs."""
        return (
            f"S={self.state_dim} A={self.action_dim} hidden={self.n_hidden} wires={self.n_wires} "
            f"gamma={self.gamma} k={self.advantage_k} alpha={self.alpha} c={self.smoothing_c} "
            f"thinks={self.thinks_per_action} update={self.update}"
        )
