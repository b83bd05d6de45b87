"""Typed configuration of the WFNN learner (one frozen dataclass per component)."""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import logging
import math
import re
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from wfnn_common.checks import ConfigError as ConfigError  # re-exported: every config user imports it here
from wfnn_common.checks import _is_int
from wfnn_common.checks import check_fields as check_fields
from wfnn_common.checks import parse_json as parse_json
from wfnn_common.symmetry import Symmetry

ExplorationKind = Literal["none", "uniform", "gaussian", "smooth", "pink"]
log = logging.getLogger(__name__)
_told_whole: set[str] = set()
"""Specs whose whole-number ranges were warned of (once each, a few: statuses repeat configs)."""


def _is_minus_zero(value: Any) -> bool:
    return isinstance(value, float) and value == 0.0 and math.copysign(1.0, value) < 0.0


@dataclass(frozen=True, kw_only=True)
class ExplorationConfig:
    """How `act` perturbs the best wire's action (thesis Sections 3.4, 6.4.1, 6.7)."""

    kind: ExplorationKind = "uniform"
    """`uniform`: replace the action by a uniform random one with probability `p` (Section 3.4);
    `gaussian`: add N(0, sigma) noise, as on the robots; `smooth`: add smoothly varying noise
    (an Ornstein-Uhlenbeck process with time constant `tau_steps`); `pink`: add noise whose power
    falls as 1/frequency up to periods of about `tau_steps` (`exploration.Explorer`); `none`: greedy."""
    p: float = 0.1
    """Probability of a uniform random action (kind `uniform`)."""
    sigma: float = 0.1
    """Noise standard deviation in scaled action units, where the declared range is [-1, 1]."""
    tau_steps: float = 10.0
    """Correlation time of the smooth noise, in actions; the pink noise's longest."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.kind not in ("none", "uniform", "gaussian", "smooth", "pink"):
            kinds = "none, uniform, gaussian, smooth or pink"
            raise ConfigError(f"exploration.kind must be {kinds}, got {self.kind!r:.60}")
        if not 0.0 <= self.p <= 1.0:
            raise ConfigError(f"exploration.p must be in [0, 1], got {self.p}")
        if not 0.0 <= self.sigma <= 100.0:
            raise ConfigError(f"exploration.sigma must be in [0, 100], got {self.sigma}")
        if not 1.0 <= self.tau_steps <= 1e6:
            raise ConfigError(f"exploration.tau_steps must be in [1, 1e6], got {self.tau_steps}")


@dataclass(frozen=True, kw_only=True)
class DeepConfig:
    """The deep wire-fitting learner's own fields (used where `LearnerConfig.learner` is "deep").

    Each of two critics is a state trunk (an MLP of `hidden` ReLU layers) with two heads: the
    wire head gives `n_wires` actions (tanh, in the scaled range [-1, 1]); the value head scores
    each (trunk features, wire action) pair through `value_layers` ReLU layers of `value_hidden`,
    so wire values depend on their actions. Q(x, u) is Eq 3.1's wire-fitting interpolation of critic 1's
    wires, with the smoothing term on the wires' values min-max normalised per state.
    """

    hidden: tuple[int, ...] = (128, 128)
    """Widths of the state trunk's ReLU layers."""
    value_hidden: int = 64
    """Width of the value head's ReLU layers (the first sees trunk features and one wire action)."""
    value_layers: int = 1
    """ReLU layers of the value head. With one, a wire's value is a sum of ridges relu(a(h) + w . u)
    whose directions w in the action space are the same in every state (only their offsets a(h)
    follow the state); a second layer lets the shape of Q over actions change with the state, as
    a critic with the action at its input (TD3's, Q3C's) can."""
    layer_norm: bool = True
    """Normalise the inputs of the trunk's ReLUs (LayerNorm without learned scale)."""
    lr: float = 3e-4
    """Adam's step size."""
    grad_clip: float = 10.0
    """Largest gradient norm of one update (larger gradients are scaled down); 0 disables, but for
    a bound of 1e18 that keeps Adam's float32 moments finite (`deep_torch.GRAD_NORM_LIMIT`)."""
    tau: float = 0.005
    """Polyak averaging rate of the target critics."""
    target_noise: float = 0.2
    """Standard deviation of the smoothing noise on the next action, in scaled units."""
    target_noise_clip: float = 0.5
    """The smoothing noise is clipped to +-this."""
    separation: float = 0.1
    """Weight of the term that keeps a state's wires apart: the mean over wire pairs of
    1 / (distance + 0.1), in scaled action units."""
    separate_best: bool = True
    """Whether the separation term moves a state's best wire too; false holds the best wire
    still in its pairs (only the other wire is pushed), so that the greedy action is placed by
    the values alone."""
    tanh_limit: float = 0.0
    """Where set, the wire head's inputs to tanh beyond +-this are penalised (squared excess),
    so that a push that never relents (separation's, under Adam's normalised steps) cannot
    drive wires deep into tanh's flat ends, where its slope all but vanishes (below 0.002
    beyond 0.999) and float32 finally rounds them to the range's bounds; 3 keeps wires within
    0.995 of the bounds. 0 disables."""
    top_k: int = 0
    """Q(x, u) interpolates only the `top_k` wires of largest weight (nearest u, with the
    smoothing term), as Q3C does, so that far wires neither shape Q there nor learn from it;
    0, or at least n_wires, interpolates all wires. The greedy action (the best wire) is the same
    either way."""
    popart_rate: float = 0.0
    """Where set, the critics learn values normalised by running statistics of their targets, and
    this is the statistics' step size per update (PopArt, van Hasselt et al. 2016): when the
    statistics move, the value heads' output layers are rescaled so that every Q stays as it was,
    and `act`'s weights carry the values in the task's units. The weights then need not grow with
    the reward's scale (Adam moves weights by about `lr` per step, so values of thousands took
    thousands of times as many steps as values of one); the separation, tanh-limit and bc terms
    keep their weight against the values in the task's units, which still depends on that scale.
    The scale is bounded below and above (`deep_net.POPART_MIN_STD` and the constants beside it).
    0 learns the values as they are."""
    n_step: int = 1
    """Returns over this many consecutive experiences: each experience is followed by the first
    one stored after it that starts exactly from its next state, whichever client sent it; the
    return is cut at a terminal or where none was stored."""
    warmup: int = 1000
    """Actions of a learner that are uniformly random, before its own choices explore."""
    device: str = "cpu"
    """Where torch trains: "cpu", "cuda" or "cuda:N" (`act` always runs on numpy)."""
    compile: bool = False
    """Compile the update with torch.compile: the same arithmetic, about 1.4 times as fast on a
    CPU here, after a one-off compile of 5 to 30 s in the first update (so not for a learner
    that thinks in a robot's tick). Needs a C++ compiler; where compiling fails, training goes
    on uncompiled with a warning."""

    def __post_init__(self) -> None:
        check_fields(self)
        checks: list[tuple[bool, str]] = [
            (1 <= len(self.hidden) <= 8 and all(1 <= h <= MAX_HIDDEN for h in self.hidden),
             f"deep.hidden must be 1 to 8 widths in [1, {MAX_HIDDEN}]"),
            (1 <= self.value_hidden <= MAX_HIDDEN, f"deep.value_hidden must be in [1, {MAX_HIDDEN}]"),
            (1 <= self.value_layers <= 8, "deep.value_layers must be in [1, 8]"),
            (0.0 < self.lr <= 1.0, "deep.lr must be in (0, 1]"),
            (0.0 <= self.grad_clip <= 1e6, "deep.grad_clip must be in [0, 1e6]"),
            (0.0 < self.tau <= 1.0, "deep.tau must be in (0, 1]"),
            (0.0 <= self.target_noise <= 10.0, "deep.target_noise must be in [0, 10]"),
            (0.0 <= self.target_noise_clip <= 10.0, "deep.target_noise_clip must be in [0, 10]"),
            (0.0 <= self.separation <= 1e3, "deep.separation must be in [0, 1000]"),
            (0.0 <= self.tanh_limit <= 20.0, "deep.tanh_limit must be in [0, 20]"),
            (0 <= self.top_k <= MAX_WIRES, f"deep.top_k must be in [0, {MAX_WIRES}]"),
            (0.0 <= self.popart_rate <= 1.0, "deep.popart_rate must be in [0, 1]"),
            (1 <= self.n_step <= 100, "deep.n_step must be in [1, 100]"),
            (0 <= self.warmup <= 10_000_000, "deep.warmup must be in [0, 1e7]"),
            (self.device == "cpu" or self.device == "cuda" or
             (self.device.startswith("cuda:") and self.device[5:].isascii() and self.device[5:].isdigit()
              and len(self.device) <= 8),
             f"deep.device must be cpu, cuda or cuda:N, got {self.device[:40]!r}"),
        ]  # fmt: skip
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"{message} (deep config: {self})")

    @classmethod
    def from_dict(cls, data: Any) -> DeepConfig:
        """A DeepConfig from its JSON form; anything else is a ConfigError."""
        if not isinstance(data, dict):
            raise ConfigError(f"deep must be a JSON object, got {type(data).__name__}")
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ConfigError(f"unknown DeepConfig fields: {_names(unknown)}")
        data = dict(data)
        if isinstance(data.get("hidden"), list):
            data["hidden"] = tuple(data["hidden"])
        return cls(**data)


LEARNERS = ("thesis", "deep")
POSITIVE_REWARD_THRESHOLD = 1.5
"""The thesis' learner's divergence threshold on a task whose rewards may be positive (`for_task`)."""
DEEP_DEFAULTS: dict[str, Any] = {
    "gamma": 0.99, "advantage_k": 1.0, "thinks_per_action": 1, "batch_size": 256, "n_wires": 8,
    "smoothing_c": 0.1, "squash_reward": False, "divergence_threshold": 1e4,
    "exploration": ExplorationConfig(kind="smooth", sigma=0.1, tau_steps=10.0),
}  # fmt: skip
"""The shared fields' defaults for the deep learner, where they differ from the thesis' (whose
gamma 0.8, 200 thinks per action and squashed rewards suit one-experience SGD on a small net)."""


MAX_SYMMETRIES = 16
"""Most symmetries a config declares (a task's mirror images; each multiplies what is learned)."""
MAX_CONFIG_JSON = 1 << 16
"""Longest config JSON (`to_json`): the longest string a protocol message carries
(`wfnn_io.protocol.MAX_STRING`)."""
MAX_STATE_DIM = 1024
MAX_ACTION_DIM = 64
MAX_HIDDEN = 4096
MAX_WIRES = 1024
MAX_THINKS = 1_000_000
_RANGES = ("state_low", "state_high", "action_low", "action_high")
"""The spec's fields that say what the network's inputs and outputs mean (`spec_difference`)."""


def _names(unknown: set[Any]) -> str:
    """Unknown field names in a refusal: the first 10, none longer than 40 characters."""
    names = sorted(str(name)[:40] for name in unknown)
    return str(names[:10]) + (f" ({len(names)} in all)" if len(names) > 10 else "")


def _shown(value: Any) -> str:
    """A spec field's value in a refusal: lists as lists, none longer than 60 characters."""
    return str(list(value) if isinstance(value, tuple) else value)[:60]


MAX_SAVED_COUNT = 10**15
"""The largest count (thinks, actions, optimiser steps) a saved learner may claim: more than any
run makes, and exact in a float64."""
MAX_BATCH = 1 << 20
MAX_REPLAY_BYTES = 8 << 30
MAX_PARAMS = 4_000_000
"""Parameters of the network `act` uses, either learner's: they travel in one snapshot (float64,
at most 32 MiB with the rest)."""
MAX_WORK = 1 << 24
"""Largest batch_size x (numbers each minibatch row keeps through an update): for the deep
learner state_dim + sum(deep.hidden) + n_wires x (value_layers x value_hidden + n_wires + action_dim), in the
trunk and in the value head (4 bytes each, for both critics, with gradients); for the thesis'
learner's minibatch update state_dim + 2 n_hidden + n_wires x (5 action_dim + 8), its layers,
their errors and the interpolation's terms."""
MIN_HALF_RANGE = 1e-12
"""Narrowest half-width of a state or action range: scaling divides by it."""
MIN_ADVANTAGE_K = 1e-3
"""Smallest advantage_k: advantage learning divides the target's advantage by k, and the
minibatch updates run in float32, where a k below its smallest normal number (1.2e-38) made the
first update's weights NaN; 1e-3 costs three of the eight orders of magnitude that MAX_REWARD
leaves below float32's largest number."""
MIN_EPS = 1e-20
"""Smallest wire-fitting epsilon: the float32 updates divide by it (1 / eps bounds a wire's weight),
and an eps that float32 rounds to 0 made the first update's weights NaN where an action lay on a
wire; 1e-20 leaves the weights times the values far below float32's largest number."""
MIN_DEEP_EPS = 1e-12
"""Smallest wire-fitting epsilon of the deep learner: torch differentiates its weights 1 / d through
their square, which in float32 overflowed (to infinity, then NaN in every weight after one update)
for an action exactly on the best wire once 1 / eps passed about 1.8e19; at 1e-12 the square stays
below 1e24."""
MAX_SEED = (1 << 62) - 1
"""Largest seed: numpy and torch take it, and benchmarks add a seed number to it."""
"""Upper limits of a learner config: a config also arrives from the network, and one that asks
for more memory or work than any robot here needs is refused rather than attempted."""


@dataclass(frozen=True, kw_only=True)
class LearnerConfig:
    """Everything that defines a WFNN learner. Defaults are the thesis' (Section 4.4).

    `learner` names the learner: "thesis" (the thesis' network and its one-experience updates)
    or "deep" (deep wire fitting, `deep` holds its own fields; `for_task(..., learner="deep")`
    starts from `DEEP_DEFAULTS`). Fields marked (thesis) are used by the thesis' learner only.
    """

    state_low: tuple[float, ...]
    """Lower end of each state variable's declared range (physical units); mapped to -1."""
    state_high: tuple[float, ...]
    """Upper end of each state variable's declared range; mapped to +1."""
    action_low: tuple[float, ...]
    """Lower end of each action variable's range; actions are always clipped into it."""
    action_high: tuple[float, ...]
    """Upper end of each action variable's range."""
    learner: Literal["thesis", "deep"] = "thesis"
    """Which learner: "thesis" or "deep"."""
    n_hidden: int = 10
    """Hidden tanh neurons (thesis)."""
    n_wires: int = 9
    """Wires (action, value pairs) output by the network for each state."""
    gamma: float = 0.8
    """Discount factor."""
    advantage_k: float = 0.2
    """Advantage learning factor k of Eq 4.1; k = 1 is one-step Q-learning."""
    alpha: float = 0.25
    """(thesis) Global learning rate; each layer uses alpha / sqrt(fan-in), bias included."""
    smoothing_c: float = 0.01
    """Wire fitter smoothing factor c of Eq 3.1."""
    eps: float = 1e-4
    """Wire fitter epsilon of Eq 3.1 (keeps every distance positive)."""
    derivatives: Literal["approx", "exact"] = "approx"
    """`approx`: Eq 3.4-3.5 as in the thesis (inexact for the top wire); `exact`: the full
    derivative including the top wire's effect on every distance."""
    thinks_per_action: int = 200
    """Experience replays per action (for the deep learner: minibatch updates per experience,
    the replay ratio)."""
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
    deep: DeepConfig = field(default_factory=DeepConfig)
    """The deep learner's own fields (unused by the thesis' learner)."""
    symmetries: tuple[Symmetry, ...] = ()
    """Declared symmetries of the task: each experience learned is also learned transformed
    by each of them (e.g. the boat's mirror image). The store and logs keep only the real
    experiences; the thinks owed per action are unchanged."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.learner not in LEARNERS:
            raise ConfigError(f"learner must be one of {LEARNERS}, got {self.learner!r:.60}")
        if not isinstance(self.deep, DeepConfig):
            raise ConfigError(f"deep must be a DeepConfig, got {self.deep!r}")
        if not isinstance(self.exploration, ExplorationConfig):
            raise ConfigError(f"exploration must be an ExplorationConfig, got {self.exploration!r}")
        if not (isinstance(self.symmetries, tuple) and all(isinstance(s, Symmetry) for s in self.symmetries)):
            raise ConfigError(f"symmetries must be a tuple of Symmetry, got {self.symmetries!r}")
        s_lo, s_hi, a_lo, a_hi = self.state_low, self.state_high, self.action_low, self.action_high
        if len(s_lo) == 0 or len(s_lo) != len(s_hi):
            raise ConfigError(f"state_low/high must be non-empty and equal length, got {s_lo}, {s_hi}")
        if len(a_lo) == 0 or len(a_lo) != len(a_hi):
            raise ConfigError(f"action_low/high must be non-empty and equal length, got {a_lo}, {a_hi}")
        for name, lo, hi in (("state", s_lo, s_hi), ("action", a_lo, a_hi)):
            for i, (a, b) in enumerate(zip(lo, hi, strict=True)):
                if not (math.isfinite(a) and math.isfinite(b) and b > a):
                    raise ConfigError(f"{name} range {i} must be finite with high > low, got [{a}, {b}]")
                if not (
                    math.isfinite(0.5 * (b - a))
                    and math.isfinite(a + b)  # the range's midpoint, 0.5 (a + b), is what scaling subtracts
                    and 0.5 * (b - a) >= MIN_HALF_RANGE * max(1.0, abs(a), abs(b))
                ):
                    raise ConfigError(f"{name} range {i} [{a}, {b}] is too narrow or too wide to scale")
        if len(s_lo) > MAX_STATE_DIM or len(a_lo) > MAX_ACTION_DIM:
            raise ConfigError(f"at most {MAX_STATE_DIM} state and {MAX_ACTION_DIM} action variables, "
                              f"got {len(s_lo)} and {len(a_lo)}")  # fmt: skip
        # A stored experience: its float64 row, and where n-step returns follow links, its link.
        linked = self.learner == "deep" and self.deep.n_step > 1
        row_bytes = 8 * (2 * len(s_lo) + len(a_lo) + 2 + int(linked))
        checks: list[tuple[bool, str]] = [
            (1 <= self.n_hidden <= MAX_HIDDEN, f"n_hidden must be in [1, {MAX_HIDDEN}]"),
            (1 <= self.n_wires <= MAX_WIRES, f"n_wires must be in [1, {MAX_WIRES}]"),
            (0.0 <= self.gamma < 1.0, "gamma must be in [0, 1)"),
            (MIN_ADVANTAGE_K <= self.advantage_k <= 1.0, f"advantage_k must be in [{MIN_ADVANTAGE_K:g}, 1]"),
            (0.0 < self.alpha <= 10.0, "alpha must be in (0, 10]"),
            (0.0 <= self.smoothing_c <= 1e3, "smoothing_c must be in [0, 1000]"),
            (MIN_EPS <= self.eps <= 1.0, f"eps must be in [{MIN_EPS:g}, 1]"),
            (0.0 <= self.bc_weight <= 1.0, "bc_weight must be in [0, 1] (a fraction of the difference)"),
            (0 <= self.thinks_per_action <= MAX_THINKS, f"thinks_per_action must be in [0, {MAX_THINKS}]"),
            (1 <= self.batch_size <= MAX_BATCH, f"batch_size must be in [1, {MAX_BATCH}]"),
            (self.replay_capacity >= 1, "replay_capacity must be >= 1"),
            (
                self.replay_capacity * row_bytes <= MAX_REPLAY_BYTES,
                f"replay_capacity x experience size must be <= {MAX_REPLAY_BYTES >> 30} GiB",
            ),
            (0.0 <= self.valid_margin <= 1e12, "valid_margin must be in [0, 1e12]"),
            (math.isfinite(self.divergence_threshold), "divergence_threshold must be finite"),
            (
                0 <= self.divergence_patience <= MAX_SAVED_COUNT,
                f"divergence_patience must be in [0, {MAX_SAVED_COUNT}]",
            ),
            (0.0 < self.init_scale <= 100.0, "init_scale must be in (0, 100]"),
            (0 <= self.seed <= MAX_SEED, f"seed must be in [0, {MAX_SEED}]"),
            (self.derivatives in ("approx", "exact"), "derivatives must be 'approx' or 'exact'"),
            (self.update in ("incremental", "minibatch"), "update must be 'incremental' or 'minibatch'"),
            (self.minibatch_dtype in ("float32", "float64"), "minibatch_dtype must be float32 or float64"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"{message} (config: {self.short_repr()})")
        if self.learner == "thesis":
            n_out = self.n_wires * (len(a_lo) + 1)
            size = self.n_hidden * (len(s_lo) + 1) + n_out * (self.n_hidden + 1)  # `network.Shapes.n_params`
            if size > MAX_PARAMS:
                raise ConfigError(f"the thesis' learner's network would have {size:,} parameters, more than "
                                  f"{MAX_PARAMS:,} (config: {self.short_repr()})")  # fmt: skip
            row = len(s_lo) + 2 * self.n_hidden + self.n_wires * (5 * len(a_lo) + 8)
            if self.update == "minibatch" and self.batch_size * row > MAX_WORK:
                raise ConfigError(f"batch_size x (state_dim + 2 n_hidden + n_wires x (5 action_dim + 8)) = "
                                  f"{self.batch_size * row:,} is more than {MAX_WORK:,} for the minibatch "
                                  f"update ({self.short_repr()})")  # fmt: skip
        if self.learner == "deep":
            d, widths = self.deep, (len(s_lo), *self.deep.hidden)
            if self.eps < MIN_DEEP_EPS:
                raise ConfigError(f"eps must be in [{MIN_DEEP_EPS:g}, 1] for the deep learner, whose float32 "
                                  f"gradient squares 1 / eps (config: {self.short_repr()})")  # fmt: skip
            # Exactly `deep_net.DeepShapes.n_params`: the trunk, the wire head, the value head.
            size = sum(a * b + b for a, b in itertools.pairwise(widths))
            size += (widths[-1] + 1) * self.n_wires * len(a_lo)
            size += d.value_hidden * (widths[-1] + len(a_lo) + 2) + 1
            size += (d.value_layers - 1) * (d.value_hidden + 1) * d.value_hidden
            if size > MAX_PARAMS:
                raise ConfigError(f"the deep learner's critic would have {size:,} parameters, more than "
                                  f"{MAX_PARAMS:,} (config: {self.short_repr()})")  # fmt: skip
            row = sum(widths) + self.n_wires * (d.value_layers * d.value_hidden + self.n_wires + len(a_lo))
            if self.batch_size * row > MAX_WORK:
                raise ConfigError(f"batch_size x (state_dim + sum(deep.hidden) + n_wires x (value_layers x "
                                  f"value_hidden + n_wires + action_dim)) = {self.batch_size * row:,} is "
                                  f"more than {MAX_WORK:,} ({self.short_repr()})")  # fmt: skip
        if len(self.symmetries) > MAX_SYMMETRIES:
            raise ConfigError(f"at most {MAX_SYMMETRIES} symmetries, got {len(self.symmetries)} (each is "
                              "learned with every experience)")  # fmt: skip
        for symmetry in self.symmetries:
            try:
                symmetry.check_dims(self.state_dim, self.action_dim)
            except ValueError as exc:
                raise ConfigError(str(exc)) from exc
        # A config is carried as JSON in client statuses and server statuses: one longer than a
        # protocol string was adopted and saved, and every status after it (restarts included)
        # was refused by every receiver, so no client could follow that server again.
        if (chars := len(self.to_json())) > MAX_CONFIG_JSON:
            raise ConfigError(f"the config's JSON is {chars:,} characters, more than the "
                              f"{MAX_CONFIG_JSON:,} a status carries ({self.short_repr()})")  # fmt: skip

    @classmethod
    def for_task(cls, task: Any, learner: str = "thesis", **overrides: Any) -> LearnerConfig:
        """A config over a task's declared ranges, the learner's defaults where not overridden.

        `task` is anything with state_low, state_high, action_low and action_high (and, where
        it declares one, `valid_margin`: how far outside those ranges its states may go); the
        deep learner starts from `DEEP_DEFAULTS`, the thesis' learner from the thesis' values.

        The thesis' divergence threshold assumes rewards of at most zero, as its tasks' are. A
        task that declares `max_reward` None (unknown, as a Gymnasium task's is) or above zero
        may earn values up to 1, the bound squashed rewards keep every value within (Eq 3.6),
        so the thesis' learner then judges only values beyond `POSITIVE_REWARD_THRESHOLD`.
        """
        defaults = dict(DEEP_DEFAULTS) if learner == "deep" else {}
        if getattr(task, "valid_margin", None) is not None:
            defaults["valid_margin"] = float(task.valid_margin)
        top = getattr(task, "max_reward", 0.0)  # where not declared, the thesis' tasks: none above zero
        if learner == "thesis" and (top is None or top > 0.0):
            defaults["divergence_threshold"] = POSITIVE_REWARD_THRESHOLD
        return cls(
            state_low=tuple(task.state_low), state_high=tuple(task.state_high),
            action_low=tuple(task.action_low), action_high=tuple(task.action_high),
            **{"learner": learner, **defaults, **overrides},
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
    def sanity_limit(self) -> float:
        """Largest |scaled state| that is valid: 1 + 2 valid_margin, and what rounding adds.

        A state on its declared bound scales, (s - mid) / half, to 1 plus the rounding of the
        range's midpoint relative to its half-width: a few ulps times |mid| / half at most.
        """
        off_centre = max(
            abs(0.5 * (a + b)) / (0.5 * (b - a)) for a, b in zip(self.state_low, self.state_high, strict=True)
        )
        limit = 1.0 + 2.0 * self.valid_margin
        return limit + 4.0 * float(np.finfo(np.float64).eps) * (limit + off_centre)

    @property
    def n_outputs(self) -> int:
        """Network outputs: n_wires actions of action_dim, then n_wires values."""
        return self.n_wires * (self.action_dim + 1)

    # ----------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form of the config.

        A thesis' learner's config leaves out `learner` and `deep` (their defaults), so that
        it reads as before wherever it goes.
        """
        data = dataclasses.asdict(self)
        if self.learner == "thesis":
            del data["learner"], data["deep"]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LearnerConfig:
        """Inverse of `to_dict`; anything that does not make a valid config is a ConfigError."""
        if not isinstance(data, dict):
            raise ConfigError(f"a learner config is a JSON object, got {type(data).__name__}")
        data = dict(data)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"unknown LearnerConfig fields: {_names(unknown)}")
        try:
            if "exploration" in data and data["exploration"] is None:  # else the thesis' default, for either
                raise ConfigError("exploration must be an object of ExplorationConfig fields, got null")
            exploration = data.pop("exploration", None)
            if "deep" in data and not isinstance(data["deep"], DeepConfig):
                data["deep"] = DeepConfig.from_dict(data["deep"])
            for key in ("state_low", "state_high", "action_low", "action_high"):
                if key in data:
                    if not isinstance(data[key], list | tuple):
                        raise ConfigError(f"{key} must be a list of numbers")
                    data[key] = tuple(data[key])
            if isinstance(exploration, dict):
                unknown = set(exploration) - {f.name for f in dataclasses.fields(ExplorationConfig)}
                if unknown:
                    raise ConfigError(f"unknown ExplorationConfig fields: {_names(unknown)}")
                data["exploration"] = ExplorationConfig(**exploration)
            elif exploration is not None:
                data["exploration"] = exploration
            if "symmetries" in data:
                if not isinstance(data["symmetries"], list | tuple):
                    raise ConfigError("symmetries must be a list")
                data["symmetries"] = tuple(
                    s if isinstance(s, Symmetry) else Symmetry.from_dict(s) for s in data["symmetries"]
                )
            config = cls(**data)
        except ConfigError:
            raise
        except (ValueError, TypeError, ArithmeticError, RecursionError) as exc:
            raise ConfigError(f"not a learner config: {type(exc).__name__}: {str(exc)[:200]}") from None
        # Whole numbers and -0.0 hash as written (a spec's hash must never change under data
        # written with it), so the same ranges as a task gives them are another spec: said once.
        whole = [key for key in ("state_low", "state_high", "action_low", "action_high")
                 if any(_is_int(v) or _is_minus_zero(v) for v in getattr(config, key))]  # fmt: skip
        spec = config.spec_hash() if whole else ""
        if whole and len(_told_whole) < 16 and spec not in _told_whole:
            _told_whole.add(spec)
            log.warning("learner config %s writes %s with whole numbers (-1, not -1.0) or -0.0: its spec "
                        "hash differs from the same ranges as a task gives them, so that task's clients, "
                        "weights and logs are of another spec; write them with a decimal point, and 0.0",
                        spec, ", ".join(whole))  # fmt: skip
        return config

    @classmethod
    def from_json(cls, text: str | bytes, what: str = "learner config") -> LearnerConfig:
        """A config from JSON text (a file, a client's status); any fault is a ConfigError."""
        return cls.from_dict(parse_json(text, what))

    def to_json(self) -> str:
        """Canonical JSON (sorted keys), used for hashing and saving."""
        return json.dumps(self.to_dict(), sort_keys=True)

    def _spec(self) -> dict[str, Any]:
        """The fields the spec hash covers, each under its name."""
        spec: dict[str, Any] = {
            "state_low": self.state_low,
            "state_high": self.state_high,
            "action_low": self.action_low,
            "action_high": self.action_high,
            "n_hidden": self.n_hidden,
            "n_wires": self.n_wires,
        }
        if self.learner == "deep":  # the thesis' spec keeps its old hash: its files stay valid
            d = self.deep
            spec = {**spec, "learner": "deep", "n_hidden": 0, "hidden": d.hidden,
                    "value_hidden": d.value_hidden, "layer_norm": d.layer_norm,
                    "value_layers": d.value_layers}  # fmt: skip
        return spec

    def spec_hash(self) -> str:
        """Hash of the fields that fix the network's shape and the meaning of its inputs.

        Two learners with the same spec hash can exchange weights and experiences.
        """
        spec = self._spec()
        if spec.get("value_layers") == 1:  # one layer's spec keeps the hash it had before the field existed
            del spec["value_layers"]
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]

    def spec_difference(self, other: LearnerConfig) -> str:
        """What tells `self`'s spec from `other`'s, in words, for refusals.

        "the deep learner's, not the thesis learner's" where they are different learners; else
        "another task or ranges", and the network's fields that differ ("n_wires 8, not 4").
        """
        if self.learner != other.learner:
            return f"the {self.learner} learner's, not the {other.learner} learner's"
        mine, theirs = self._spec(), other._spec()
        differ = [k for k in mine if json.dumps(mine[k]) != json.dumps(theirs.get(k))]  # as hashed
        network = [f"{k} {_shown(mine[k])}, not {_shown(theirs.get(k))}" for k in differ if k not in _RANGES]
        parts = ["another task or ranges"] if any(k in _RANGES for k in differ) else []
        if network:
            parts.append(f"another network: {'; '.join(network)}")
        return " and ".join(parts)

    def short_repr(self) -> str:
        """One line for logs."""
        if self.learner == "deep":
            d = self.deep
            return (
                f"deep S={self.state_dim} A={self.action_dim} hidden={d.hidden} "
                f"value={d.value_hidden}x{d.value_layers} "
                f"wires={self.n_wires} gamma={self.gamma} k={self.advantage_k} lr={d.lr} "
                f"c={self.smoothing_c} thinks={self.thinks_per_action} batch={self.batch_size} "
                f"n_step={d.n_step}"
            )
        return (
            f"S={self.state_dim} A={self.action_dim} hidden={self.n_hidden} wires={self.n_wires} "
            f"gamma={self.gamma} k={self.advantage_k} alpha={self.alpha} c={self.smoothing_c} "
            f"thinks={self.thinks_per_action} update={self.update}"
        )


THESIS_ONLY_FIELDS = ("n_hidden", "alpha", "derivatives", "update", "minibatch_dtype")
"""LearnerConfig fields the deep learner does not use (it has its own under `deep`)."""


def settings(config: dict[str, Any]) -> list[tuple[str, Any]]:
    """The settings a config (as a dict, `LearnerConfig.to_dict`) learns with, for people to read.

    Only the fields its learner uses, nested ones by dotted name (`deep.hidden`,
    `exploration.sigma`); the ranges and symmetries (lists) are left out.
    """
    deep = config.get("learner") == "deep"
    out: list[tuple[str, Any]] = []
    for name, value in config.items():
        if (deep and name in THESIS_ONLY_FIELDS) or (not deep and name == "deep"):
            continue
        if isinstance(value, dict):
            out += [(f"{name}.{k}", v) for k, v in value.items()]
        elif not isinstance(value, list | tuple):
            out.append((name, value))
    return out


def with_options(config: LearnerConfig, options: dict[str, Any]) -> LearnerConfig:
    """`config` with the fields in `options` replaced.

    `deep` and `exploration` are merged field by field; anything that does not make a valid
    config is a ConfigError.
    """
    if not isinstance(options, dict):
        raise ConfigError(f"learner options must be a JSON object, got {type(options).__name__}")
    wanted = options.get("learner", config.learner)
    if wanted != config.learner and wanted in LEARNERS:  # another name is refused as any bad value is
        # Each learner starts from its own defaults (`for_task`): switching here would keep the
        # other's (a deep learner with the thesis' gamma, thinks and squashed rewards).
        raise ConfigError(f"learner options cannot change the learner ({config.learner} to {wanted}): "
                          "choose it with --learner")  # fmt: skip
    # A field this learner never reads was taken and recorded, and the run learned without it
    # (`alpha` for the deep learner, whose step is `deep.lr`).
    unread = [k for k in options if k in THESIS_ONLY_FIELDS] if config.learner == "deep" else []
    if config.learner == "thesis" and "deep" in options:
        unread = ["deep"]
    if unread:
        hint = "choose it with --learner deep" if unread == ["deep"] else "its own: deep.lr, deep.hidden"
        raise ConfigError(f"learner options {unread} are not the {config.learner} learner's ({hint})")
    data = config.to_dict()
    data.pop("symmetries")  # kept as objects: to_dict's form of them is not what from_dict takes
    for key, value in options.items():
        if key in ("deep", "exploration") and isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    if "symmetries" not in options:
        data["symmetries"] = config.symmetries
    return LearnerConfig.from_dict(data)


@dataclass(frozen=True, kw_only=True)
class LearnerOverrides:
    """Learner config fields a command line sets over a config: the one mechanism of both CLIs.

    `wfnn-client` applies them over the task's defaults, `wfnn-server` over the config it adopts
    (given, from a client or from logs). A server saves the adopted config before its overrides,
    so a flag dropped at a restart drops its effect. None leaves a field as it is; `options` (a
    JSON object of config fields, `deep` and `exploration` merged field by field) comes last.
    Values are checked by `LearnerConfig`'s own rules when the overrides are made.
    """

    seed: int | None = None
    thinks_per_action: int | None = None
    advantage_k: float | None = None
    bc_weight: float | None = None
    learning_rate: float | None = None
    """The thesis' learner's `alpha`, or the deep learner's Adam step `deep.lr`."""
    options: str = ""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.options and not isinstance(parse_json(self.options, "learner options"), dict):
            raise ConfigError("learner options must be a JSON object of learner config fields")
        # Each value by the config's own rules, for whichever learner it will meet (not known
        # yet: a server adopts its clients' config). A value one learner can hold is taken (a
        # thesis alpha of 2 is no deep lr); the config it is applied to then checks it again.
        refusals: list[str] = []
        for learner in LEARNERS:
            lo, hi = (-1.0,), (1.0,)
            probe = LearnerConfig(state_low=lo, state_high=hi, action_low=lo, action_high=hi,
                                  learner=learner)  # type: ignore[arg-type]  # fmt: skip
            try:
                with_options(probe, self._changes(probe))
            except ConfigError as exc:  # the probe's own figures would only confuse
                refusals.append(re.split(r" \((?:deep )?config: ", str(exc))[0])
        if len(refusals) == len(LEARNERS):
            said = list(dict.fromkeys(refusals))  # one rule broken for both learners is said once
            raise ConfigError(f"learner override: {'; '.join(said)}")

    def __bool__(self) -> bool:
        return any(getattr(self, f.name) not in (None, "") for f in dataclasses.fields(self))

    def apply(self, config: LearnerConfig) -> LearnerConfig:
        """`config` with these overrides (a ConfigError where the result is not a valid config)."""
        changes = self._changes(config)
        out = with_options(config, changes) if changes else config
        return with_options(out, parse_json(self.options, "learner options")) if self.options else out

    def _changes(self, config: LearnerConfig) -> dict[str, Any]:
        """The fields set, as `with_options` takes them for `config`'s learner (options apart)."""
        names = ("seed", "thinks_per_action", "advantage_k", "bc_weight")
        changes: dict[str, Any] = {n: getattr(self, n) for n in names if getattr(self, n) is not None}
        if self.learning_rate is not None:
            changes.update({"deep": {"lr": self.learning_rate}} if config.learner == "deep"
                           else {"alpha": self.learning_rate})  # fmt: skip
        return changes
