"""The WFNN learner with the act-learn-think interface, for one learner or a population.

    learner = WFNN(config)
    x = robot.state()
    while running:
        u = learner.act(x).action             # Part 1: best wire (+ exploration), real time
        x_next, r = robot.step(u)
        learner.learn(x, u, x_next, r)         # Part 1i: store the experience
        learner.think()                        # Parts 2-3: thinks_per_action replays
        x = x_next

Every method accepts one learner's arrays ([S], [A], scalars) or a population's ([P, S], ...),
and answers in the same form. States and actions are in physical units; the learner scales
them by the declared ranges.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wfnn_common.config import LearnerConfig
from wfnn_common.exploration import Explorer
from wfnn_common.kernels import Hyperparameters, act_one, think_incremental, think_incremental_one
from wfnn_common.network import Params, Scaler, Shapes, forward, init_params, layer_rates, reinit, split_wires
from wfnn_common.replay import Experiences, ReplayBuffer
from wfnn_common.update import UpdateStats, squash_reward, wfnn_update
from wfnn_common.wirefit import wirefit_q

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest finite float32: the deep learner trains in float32, where anything larger is infinite."""
RANDOM_STATE = ("random_seed", "random_weights", "random_replay", "random_exploration", "exploration_noise")
"""A learner's `random_state`: the seed its streams began from, its three generators' states
(`generator_state`) and the exploration noise [population, action_dim]."""


def generator_state(rng: np.random.Generator) -> NDArray[np.uint64]:
    """A PCG64 generator's state as [6] uint64.

    Its state and increment (128 bits each, high word first), whether a 32-bit half is buffered,
    and that half.
    """
    bits = rng.bit_generator.state
    if bits.get("bit_generator") != "PCG64":
        raise ValueError(f"only PCG64 generators are saved, not {bits.get('bit_generator')}")
    state, inc = bits["state"]["state"], bits["state"]["inc"]
    words = (state >> 64, state & WORD, inc >> 64, inc & WORD, bits["has_uint32"], bits["uinteger"])
    return np.array(words, dtype=np.uint64)


def generator_state_from(value: Any, name: str) -> dict[str, Any]:
    """Inverse of `generator_state`: the bit generator's state dict (ValueError if not one)."""
    words = np.asarray(value)
    if words.dtype != np.uint64 or words.shape != (6,) or int(words[4]) > 1 or int(words[5]) > 0xFFFFFFFF:
        raise ValueError(f"training state {name}: {words.dtype} {words.shape}, not a generator's state")
    if not int(words[3]) & 1:  # PCG64's increment is odd; one of 0 draws 0 for ever
        raise ValueError(f"training state {name}: an even increment, not a generator's state")
    w = [int(v) for v in words]
    return {"bit_generator": "PCG64", "state": {"state": (w[0] << 64) | w[1], "inc": (w[2] << 64) | w[3]},
            "has_uint32": w[4], "uinteger": w[5]}  # fmt: skip


WORD = (1 << 64) - 1
NOISE_DEVIATIONS = 20
"""The most smooth exploration noise a saved state may hold, in deviations (sigma)."""

MAX_INDICES = 1 << 22
"""Most replay indices a minibatch think draws at once (64 MiB with their random numbers)."""
MAX_REWARD = 1e30
"""Largest reward magnitude learned. The deep learner trains in float32 (largest 3.4e38): its
values reach max |r| / (1 - gamma), its targets add n-step returns, and the loss's gradient
doubles their difference, so rewards near float32's largest turned its weights NaN for good;
1e30 leaves those eight orders of magnitude."""
LEARN_BLOCK_FLOATS = 1 << 22
"""About how many numbers (32 MiB) `learn_many` makes at once, images included."""


def _flags(a: ArrayLike, what: str) -> NDArray[np.bool_]:
    """`a` as booleans: bools, or numbers that are 0 or 1; anything else is a ValueError.

    numpy takes any non-empty text or non-zero number for True: flags read from a CSV or JSON
    log as "False", or a NaN, were stored as terminal, their next states dropped.
    """
    arr = np.asarray(a)
    if arr.dtype == np.bool_:
        return arr
    if arr.dtype.kind in "iuf" and bool(((arr == 0) | (arr == 1)).all()):
        return arr != 0
    raise ValueError(f"{what} must be booleans or 0/1, got {str(a)[:60]!r}")


def exactly(a: ArrayLike, shape: tuple[int | None, ...], what: str, dtype: type = np.float64) -> Any:
    """`a` as an array of exactly `shape` (None: any length), else a ValueError naming it.

    Blocks of experiences are not reshaped into place: [S, N] states for [N, S] ones were taken
    as other states, without a word. Flags (dtype bool) are booleans or 0/1 (`_flags`).
    """
    arr = np.asarray(a, dtype=dtype) if dtype is not np.bool_ else _flags(a, what)
    if arr.ndim != len(shape) or any(w is not None and w != n for w, n in zip(shape, arr.shape, strict=True)):
        wanted = ", ".join("N" if w is None else str(w) for w in shape)
        raise ValueError(f"{what}: expected shape [{wanted}], got {list(np.shape(a))}")
    return arr


class ActResult(NamedTuple):
    """What `act` chose.

    Attributes:
        action: executed action, physical units, [A] or [P, A].
        value: value of the best wire (Q of the greedy action): a numpy scalar or [P].
        valid: whether the state passed the sanity limits, [] or [P].
        explored: whether exploration changed the action, [] or [P].
        diverged: whether the divergence monitor fired on this action, [] or [P].
    """

    action: FloatArray
    value: Any
    valid: Any
    explored: Any
    diverged: Any


class DivergenceMonitor:
    """Section 7.6.2: chosen actions' values persistently above a threshold mean divergence.

    The maximum reward is zero, so values should not rise above zero; a run of `patience`
    consecutive chosen-action values above `threshold` is judged divergence, and a value that
    is not finite (weights gone NaN or infinite, which never recover) at once.
    """

    def __init__(self, population: int, threshold: float, patience: int) -> None:
        self.threshold = threshold
        self.patience = patience
        self.run = np.zeros(population, dtype=np.int64)

    def observe(self, value: FloatArray, mask: BoolArray | None = None) -> BoolArray:
        """Record the chosen actions' values [P]; returns the learners judged diverged now.

        Learners where `mask` is False (an invalid state, acted on from a best estimate) are
        skipped: their run of high values neither grows nor ends.
        """
        high = ~(value <= self.threshold)  # NaN too
        run = np.where(np.isfinite(value), (self.run + 1) * high, max(self.patience, 1))  # NaN: at once
        self.run = run if mask is None else np.where(mask, run, self.run)
        diverged = self.run >= self.patience if self.patience > 0 else np.zeros_like(high)
        if diverged.any():
            self.run[diverged] = 0
        return diverged

    def first_diverged(self, values: FloatArray) -> int:
        """`observe` one learner's (population 1) chosen-action values [T], in order, in one pass.

        Returns the index of the first value at which it is judged diverged (the run restarts
        there, and the values after it are not observed: they came from the weights a reset
        replaces), or -1 where none is, as T calls of `observe` would.
        """
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size == 0:
            return -1
        finite = np.isfinite(v)
        high = ~(v <= self.threshold)  # NaN too
        # `observe`'s recurrence unrolled: a run restarts at each finite value at or below the
        # threshold (at 0) and at each non-finite one (at max(patience, 1)), and grows by one a value.
        index = np.arange(v.size)
        last = np.maximum.accumulate(np.where(~finite | ~high, index, -1))
        start = np.where(finite, 0, max(self.patience, 1))
        run = np.where(last >= 0, start[last] + index - last, self.run[0] + index + 1)
        if self.patience > 0:
            hit = np.flatnonzero(run >= self.patience)
            if hit.size:
                self.run[0] = 0
                return int(hit[0])
        self.run[0] = int(run[-1])
        return -1


def greedy_wires(
    params: Params, x: FloatArray, n_wires: int, action_dim: int
) -> tuple[FloatArray, FloatArray]:
    """Best wire for each learner's scaled state x [P, S] -> (action [P, A], value [P])."""
    n_act = n_wires * action_dim
    if params.population == 1:  # the robot's case: plain matrix-vector products are fastest
        hidden = np.tanh(params.W1[0] @ x[0] + params.b1[0])
        out = np.tanh(params.W2[0] @ hidden + params.b2[0])
        best = int(out[n_act:].argmax())
        return out[None, best * action_dim : (best + 1) * action_dim], out[None, n_act + best]
    hidden = np.tanh(np.matmul(params.W1, x[:, :, None])[:, :, 0] + params.b1)
    out = np.tanh(np.matmul(params.W2, hidden[:, :, None])[:, :, 0] + params.b2)
    wire_u, wire_q = split_wires(out, n_wires, action_dim)
    best = np.argmax(wire_q, axis=1)
    rows = np.arange(x.shape[0])
    return wire_u[rows, best], wire_q[rows, best]


class WFNN:
    """A population of P independent WFNN learners sharing one config (seeds differ).

    The thesis' learner; `wfnn_common.deep.DeepWFNN` (the deep learner) shares its interface
    and everything here that does not depend on the network (scaling, sanity limits, acting
    on estimates, exploration, the divergence monitor, the replay buffer and symmetries).
    """

    def __init__(self, config: LearnerConfig, population: int = 1, params: Params | None = None):
        if population < 1:
            raise ValueError(f"population must be >= 1, got {population}")
        self.config = config
        self.population = population
        seeds = np.random.SeedSequence(config.seed).spawn(3)
        self._weights_rng = np.random.default_rng(seeds[0])
        self._replay_rng = np.random.default_rng(seeds[1])
        self.state_scaler = Scaler(config.state_low, config.state_high)
        self.action_scaler = Scaler(config.action_low, config.action_high)
        self._action_low = np.asarray(config.action_low, dtype=np.float64)
        self._action_high = np.asarray(config.action_high, dtype=np.float64)
        """The action range: an action mapped back from [-1, 1] can round one step past it."""
        self.buffer = ReplayBuffer(population, config.replay_capacity, config.state_dim, config.action_dim)
        self.explorer = Explorer(
            config.exploration, population, config.action_dim, np.random.default_rng(seeds[2])
        )
        self.monitor = DivergenceMonitor(population, config.divergence_threshold, config.divergence_patience)
        self._limit = config.sanity_limit
        self._last_valid = np.zeros((population, config.state_dim))
        self.resets = np.zeros(population, dtype=np.int64)
        """Divergence resets per learner."""
        self.rejected = np.zeros(population, dtype=np.int64)
        """Experiences refused by the sanity limits per learner."""
        self.thinks = np.zeros(population, dtype=np.int64)
        """Weight updates performed per learner."""
        self.last_think = UpdateStats(np.zeros(population), np.zeros(population))
        self._init_network(params)

    def _init_network(self, params: Params | None) -> None:
        """The thesis' network: given weights or fresh ones, and its compiled `act` loaded."""
        config, population = self.config, self.population
        if params is not None and params.shapes != Shapes.of(config):
            raise ValueError(f"weights for a network of {params.shapes} do not fit this config's "
                             f"{Shapes.of(config)}")  # fmt: skip
        self.params = params if params is not None else init_params(config, population, self._weights_rng)
        if self.params.population != population:
            raise ValueError(f"params hold {self.params.population} networks, expected {population}")
        self.rates = layer_rates(config)
        self.hyperparameters = Hyperparameters.of(config)
        """The compiled think's record of the config, built once: the config is frozen."""
        if population == 1:  # load the compiled act now, not in a robot's first control tick
            W1, b1, W2, b2 = self.params.single
            z = np.zeros(config.state_dim)
            act_one(W1, b1, W2, b2, z, z, z + 1.0, 1.0, config.n_wires, config.action_dim, z.copy(),
                    np.empty(W1.shape[0]), np.empty(W2.shape[0]))  # fmt: skip

    # ------------------------------------------------------------------ shapes
    def _check_snapshot(self, params: Any) -> None:
        """ValueError unless `params` are weights of this learner's network and population.

        `act`'s compiled kernels take their sizes from the weights: another network's would be
        read past their ends. A snapshot shares its learner's shapes, so the check is one `is`.
        """
        mine = self.params
        shapes = getattr(params, "shapes", None)
        if type(params) is not type(mine) or (shapes is not mine.shapes and shapes != mine.shapes):
            raise ValueError(f"weights of another network ({shapes or type(params).__name__}) do not fit "
                             f"this learner's {mine.shapes}")  # fmt: skip
        if params.flat.shape[0] != mine.flat.shape[0]:
            raise ValueError(f"weights of a population of {params.flat.shape[0]} do not fit this learner's "
                             f"{mine.flat.shape[0]}")  # fmt: skip

    def _rows(self, a: ArrayLike, width: int) -> tuple[FloatArray, bool]:
        arr = np.asarray(a, dtype=np.float64)
        single = arr.ndim == 1
        arr = arr.reshape(1, -1) if single else arr
        if arr.shape != (self.population, width):
            raise ValueError(f"expected shape [{width}] or [{self.population}, {width}], got {np.shape(a)}")
        return arr, single

    def _per_learner(self, a: ArrayLike, dtype: type) -> NDArray[Any]:
        arr: NDArray[Any] = (
            _flags(a, "terminal and valid flags") if dtype is np.bool_ else np.asarray(a, dtype=dtype)
        )
        if arr.ndim == 0:
            arr = np.full(self.population, arr, dtype=dtype)
        if arr.shape != (self.population,):
            raise ValueError(f"expected a scalar or shape [{self.population}], got {arr.shape}")
        return arr

    # ------------------------------------------------------------------ sanity
    def scale_state(self, state: FloatArray) -> tuple[FloatArray, BoolArray]:
        """Scaled states [P, S] and their validity [P] (finite and within the sanity limits)."""
        x = self.state_scaler.to_unit(state)
        valid: BoolArray = np.asarray((np.abs(x) <= self._limit).all(axis=1))
        return x, valid

    def _best_estimate(self, x: FloatArray, valid: BoolArray) -> FloatArray:
        """For invalid states: the last valid value in place of non-finite entries, clipped."""
        if valid.all():
            self._last_valid = x
            return x
        fixed = np.clip(np.where(np.isfinite(x), x, self._last_valid), -self._limit, self._limit)
        self._last_valid = np.where(valid[:, None], x, self._last_valid)
        return fixed

    # ------------------------------------------------------------------ act
    def act(self, state: ArrayLike, explore: bool = True, params: Any = None) -> ActResult:
        """Part 1: the best wire's action for each state, optionally explored.

        Invalid states (non-finite or beyond the sanity limits) are acted on with the best
        estimate; `learn` refuses them. Divergence is monitored on the greedy value and a
        diverged learner's weights are reset (experiences kept) unless `params` (a snapshot)
        was given: then the caller sees `diverged` and decides.
        """
        cfg = self.config
        if params is not None and params is not self.params:
            self._check_snapshot(params)
        s = np.asarray(state, dtype=np.float64)
        single = s.ndim == 1
        if single and self.population == 1 and s.shape[0] == cfg.state_dim:
            return self._act_one(s, explore, params or self.params)
        if s.ndim == 0 or s.shape[-1] != cfg.state_dim or s.size != self.population * cfg.state_dim:
            raise ValueError(
                f"expected state shape [{cfg.state_dim}] or [{self.population}, {cfg.state_dim}], "
                f"got {s.shape}"
            )
        x = ((s - self.state_scaler.mid) / self.state_scaler.half).reshape(self.population, cfg.state_dim)
        # One comparison covers both limits: NaN compares False, inf exceeds the limit.
        valid: BoolArray = np.asarray((np.abs(x) <= self._limit).all(axis=1))
        x = self._best_estimate(x, valid)
        greedy, value = self._greedy(params or self.params, x)
        bad: BoolArray = np.asarray(~np.isfinite(greedy).all(axis=1))
        if bad.any():  # weights gone non-finite: mid-range this once (the monitor resets them)
            greedy = np.where(bad[:, None], 0.0, greedy)
            value = np.where(bad, np.nan, value)
        if explore:
            u = self._explore(greedy)
            explored = (u != greedy).any(axis=1)
        else:
            u, explored = greedy, np.zeros(self.population, dtype=np.bool_)
        diverged = self.monitor.observe(value, valid)
        if params is None and diverged.any():
            self.reset_weights(diverged)
        action = self._in_range(u * self.action_scaler.half + self.action_scaler.mid)
        if single:
            return ActResult(action[0], value[0], valid[0], explored[0], diverged[0])
        return ActResult(action, value, valid, explored, diverged)

    def _greedy(self, params: Any, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Best wire for scaled states x [P, S] -> (action [P, A], value [P])."""
        return greedy_wires(params, x, self.config.n_wires, self.config.action_dim)

    def _explore(self, greedy: FloatArray) -> FloatArray:
        """Explored actions [P, A] for greedy ones (scaled units)."""
        return self.explorer(greedy)

    def _act_one(self, s: FloatArray, explore: bool, params: Params) -> ActResult:
        """`act` for a single learner: the robot's hot path, with as few array calls as possible.

        The thesis' network runs in one compiled kernel (`kernels.act_one`).
        """
        cfg = self.config
        W1, b1, W2, b2 = params.single
        # Fresh buffers per call: act may run on several threads (a snapshot each).
        x, hidden, out = np.empty(cfg.state_dim), np.empty(W1.shape[0]), np.empty(W2.shape[0])
        scaler = self.state_scaler
        valid, best, value = act_one(W1, b1, W2, b2, s, scaler.mid, scaler.half, self._limit,
                                     cfg.n_wires, cfg.action_dim, x, hidden, out)  # fmt: skip
        if valid:
            self._last_valid = x[None]
        else:  # act on the best estimate: already scaled, so through an identity scaling
            x = self._best_estimate(x[None], np.zeros(1, dtype=np.bool_))[0]
            identity = np.zeros(cfg.state_dim), np.ones(cfg.state_dim)
            _, best, value = act_one(W1, b1, W2, b2, x, *identity, np.inf, cfg.n_wires, cfg.action_dim,
                                     x.copy(), hidden, out)  # fmt: skip
        return self._finish_one(out[best * cfg.action_dim : (best + 1) * cfg.action_dim], value, valid,
                                explore, params)  # fmt: skip

    def _finish_one(self, u: FloatArray, value: float, valid: bool, explore: bool, params: Any) -> ActResult:
        """The rest of a single learner's `act` after its greedy wire (u [A] scaled, its value)."""
        finite = bool(np.isfinite(value)) and bool(np.isfinite(u).all())
        if not finite:  # weights gone non-finite: the middle of the range this once, then reset below
            u = np.where(np.isfinite(u), u, 0.0)
        explored = False
        if explore:
            greedy = u
            u = self._explore(greedy[None])[0]
            explored = bool((u != greedy).any())
        monitor = self.monitor
        diverged = False
        if not valid:
            pass  # an estimated state: the run of high values neither grows nor ends
        elif not value <= monitor.threshold or not finite:
            # A non-finite value or wire (weights gone NaN or infinite) never recovers: at once.
            monitor.run[0] = monitor.run[0] + 1 if finite else max(monitor.patience, 1)
            if 0 < monitor.patience <= monitor.run[0]:
                monitor.run[0] = 0
                diverged = True
                if params is self.params:
                    self.reset_weights(np.ones(1, dtype=np.bool_))
        else:
            monitor.run[0] = 0
        action = self._in_range(u * self.action_scaler.half + self.action_scaler.mid)
        return ActResult(action, np.float64(value), np.bool_(valid), np.bool_(explored), np.bool_(diverged))

    def _in_range(self, action: FloatArray) -> FloatArray:
        """`action` (physical units) clipped into the action range, in place (rounding of the mapping)."""
        np.maximum(action, self._action_low, out=action)
        return np.minimum(action, self._action_high, out=action)

    # ------------------------------------------------------------------ learn
    def to_experiences(
        self,
        state: ArrayLike,
        action: ArrayLike,
        next_state: ArrayLike,
        reward: ArrayLike,
        terminal: ArrayLike = False,
        valid: ArrayLike = True,
    ) -> tuple[Experiences, BoolArray]:
        """Scale one experience per learner and check it: -> (experiences [P, ...], ok [P])."""
        s, _ = self._rows(state, self.config.state_dim)
        a, _ = self._rows(action, self.config.action_dim)
        sn, _ = self._rows(next_state, self.config.state_dim)
        r = self._per_learner(reward, np.float64)
        term = self._per_learner(terminal, np.bool_)
        ok = self._per_learner(valid, np.bool_).copy()
        return self._check(s, a, sn, r, term, ok)

    def _check(
        self, s: FloatArray, a: FloatArray, sn: FloatArray, r: FloatArray, term: BoolArray, ok: BoolArray
    ) -> tuple[Experiences, BoolArray]:
        """Scale and sanity-check rows of experiences [N, ...]; `ok` [N] is updated in place."""
        x, x_ok = self.scale_state(s)
        xn, xn_ok = self.scale_state(sn)
        u = self.action_scaler.to_unit(a)
        ok &= x_ok & (xn_ok | term) & np.isfinite(u).all(axis=1) & (np.abs(r) <= MAX_REWARD)  # NaN fails
        # Actions are executed clipped, so they are learned clipped.
        u = np.clip(np.nan_to_num(u), -1.0, 1.0)
        xn = np.where(term[:, None], 0.0, np.nan_to_num(xn))
        return Experiences(np.nan_to_num(x), u, xn, r, term), ok

    def learn(
        self,
        state: ArrayLike,
        action: ArrayLike,
        next_state: ArrayLike,
        reward: ArrayLike,
        terminal: ArrayLike = False,
        valid: ArrayLike = True,
    ) -> BoolArray:
        """Part 1i: store the experience (x_t, u_t, x_t+1, r_t) of each learner.

        `valid` False marks an irrelevant or suspect transition (e.g. a target jump) that must
        not be learned. Returns which learners stored it ([] or [P]).
        """
        exp, ok = self.to_experiences(state, action, next_state, reward, terminal, valid)
        self.buffer.add(exp, ok)
        self.rejected += ~ok & self._per_learner(valid, np.bool_)
        if self.config.symmetries:  # the mirrored experiences of those stored
            cfg = self.config
            rows = (
                self._rows(state, cfg.state_dim)[0], self._rows(action, cfg.action_dim)[0],
                self._rows(next_state, cfg.state_dim)[0], self._per_learner(reward, np.float64),
            )  # fmt: skip
            for symmetry in self.config.symmetries:
                mirrored, mirrored_ok = self.to_experiences(*symmetry(*rows), terminal, ok)
                self.buffer.add(mirrored, mirrored_ok)
        return ok[0] if np.ndim(state) == 1 else ok

    def learn_many(
        self,
        state: ArrayLike,
        action: ArrayLike,
        next_state: ArrayLike,
        reward: ArrayLike,
        terminal: ArrayLike,
    ) -> BoolArray:
        """Store a block of N experiences ([N, S], [N, A], [N, S], [N], [N]) for every learner.

        Each experience passes the same sanity limits as in `learn`; returns which were stored [N].
        """
        cfg = self.config
        s = exactly(state, (None, cfg.state_dim), "state")
        n = s.shape[0]
        a = exactly(action, (n, cfg.action_dim), "action")
        sn = exactly(next_state, (n, cfg.state_dim), "next_state")
        r = exactly(reward, (n,), "reward")
        term = exactly(terminal, (n,), "terminal", np.bool_)
        # In pieces of about LEARN_BLOCK_FLOATS numbers with their images: a block of 100,000
        # experiences under hundreds of symmetries, made and reordered at once, took gigabytes.
        row = (1 + len(cfg.symmetries)) * (2 * cfg.state_dim + cfg.action_dim + 2)
        step = max(1, LEARN_BLOCK_FLOATS // row)
        if n > step:
            return np.concatenate([self._learn_block(s[i : i + step], a[i : i + step], sn[i : i + step],
                                                     r[i : i + step], term[i : i + step])
                                   for i in range(0, n, step)])  # fmt: skip
        return self._learn_block(s, a, sn, r, term)

    def _learn_block(
        self, s: FloatArray, a: FloatArray, sn: FloatArray, r: FloatArray, term: BoolArray
    ) -> BoolArray:
        """`learn_many` of checked arrays [n, ...]."""
        cfg, n = self.config, s.shape[0]
        exp, ok = self._check(s, a, sn, r, term, np.ones(n, dtype=np.bool_))
        images, kept = [exp], [ok]
        for symmetry in cfg.symmetries:  # the mirrored experiences of those stored
            mirrored, mirrored_ok = self._check(*symmetry(s, a, sn, r), term, ok.copy())
            images.append(mirrored)
            kept.append(mirrored_ok)
        # Stored in the order `learn` stores them, each experience followed by its images, so that
        # a block and the same experiences learned one by one fill the buffer alike.
        order = np.stack(kept, axis=1).reshape(-1)  # [N x (1 + len(symmetries))], experience-major
        block = Experiences._make(
            np.stack(fields, axis=1).reshape(-1, *fields[0].shape[1:])[order]
            for fields in zip(*images, strict=True)
        )
        for i in range(self.population):
            self.buffer.extend(i, block)
        self.rejected += int(n - ok.sum())
        return ok

    # ------------------------------------------------------------------ think
    def think(self, n: int | None = None) -> UpdateStats:
        """Parts 2-3: n experience replays per learner (default thinks_per_action).

        Incremental mode: n one-experience updates. Minibatch mode: n updates of batch_size
        experiences each. Learners with no experiences yet are left unchanged.
        """
        cfg = self.config
        n = cfg.thinks_per_action if n is None else n
        active = self.buffer.count > 0
        if n <= 0 or not active.any():
            return self.last_think
        if cfg.update == "incremental":
            idx = self.buffer.sample_indices(self._replay_rng, n)
            stats = self._think_incremental(self.buffer.arrays(), idx, active, self.params)
        else:
            from wfnn_common.torch_update import minibatch_think  # torch only where needed

            # The indices of at most MAX_INDICES experiences at once: n x batch_size of them, drawn
            # together, took gigabytes for an accepted config (100,000 thinks of 4,096). Drawn in
            # parts, one learner's are those of one draw; a population's are other uniform ones.
            per_call = max(1, MAX_INDICES // (cfg.batch_size * self.population))
            parts: list[tuple[int, NDArray[np.float64], NDArray[np.float64]]] = []
            for start in range(0, n, per_call):
                k = min(per_call, n - start)
                idx = self.buffer.sample_indices(self._replay_rng, k * cfg.batch_size)
                idx = idx.reshape(self.population, k, cfg.batch_size).transpose(1, 0, 2)
                q, td = minibatch_think(
                    self.params, self.rates, self.buffer.arrays(), idx, active,
                    n_wires=cfg.n_wires, gamma=cfg.gamma, advantage_k=cfg.advantage_k,
                    c=cfg.smoothing_c, eps=cfg.eps, exact=cfg.derivatives == "exact",
                    squash=cfg.squash_reward, bc_weight=cfg.bc_weight, dtype=cfg.minibatch_dtype,
                )  # fmt: skip
                parts.append((k, q, td))
            if len(parts) > 1:  # the means over every experience used, as one call gives them
                weights = np.array([k for k, _, _ in parts], dtype=np.float64)[:, None] / n
                q = (weights * np.array([pq for _, pq, _ in parts])).sum(axis=0)
                td = (weights * np.array([ptd for _, _, ptd in parts])).sum(axis=0)
            self.thinks += active * n
            stats = UpdateStats(q, td)
        self.last_think = stats
        return stats

    def _think_incremental(
        self, exp: Experiences, idx: NDArray[np.int64], active: BoolArray, p: Params
    ) -> UpdateStats:
        kernel = think_incremental_one if self.population == 1 else think_incremental
        q, td = kernel(
            p.W1, p.b1, p.W2, p.b2, exp.state, exp.action, exp.next_state, exp.reward, exp.terminal,
            idx, active, self.hyperparameters,
        )  # fmt: skip
        self.thinks += active * idx.shape[1]
        return UpdateStats(q, td)

    def think_on(
        self, exp: Experiences, active: BoolArray | None = None, params: Params | None = None
    ) -> UpdateStats:
        """Learn from given experiences [P, T, ...] (incremental: T updates in order; minibatch: one)."""
        cfg = self.config
        if params is not None and params is not self.params:
            self._check_snapshot(params)
        self._check_given(exp)
        p = params or self.params
        active = np.ones(self.population, dtype=np.bool_) if active is None else active
        if cfg.update == "incremental":
            n = exp.reward.shape[1]
            idx = np.broadcast_to(np.arange(n, dtype=np.int64), (self.population, n))
            return self._think_incremental(exp, idx, active, p)
        reward = squash_reward(exp.reward, cfg.gamma) if cfg.squash_reward else exp.reward
        stats = wfnn_update(
            p, self.rates, exp.state, exp.action, exp.next_state, reward, exp.terminal,
            n_wires=cfg.n_wires, gamma=cfg.gamma, advantage_k=cfg.advantage_k,
            c=cfg.smoothing_c, eps=cfg.eps, derivatives=cfg.derivatives, active=active,
            bc_weight=cfg.bc_weight,
        )  # fmt: skip
        self.thinks += active
        return stats

    def _check_given(self, exp: Experiences) -> None:
        """ValueError unless `exp` are experiences [P, T >= 1, ...] fit to learn from.

        `think_on` learns what it is given, past `learn`'s checks: one NaN reward made every
        weight NaN, and the next `act` reset them all without a word.
        """
        cfg, p = self.config, self.population
        t = np.shape(exp.reward)[1] if np.ndim(exp.reward) == 2 else 0
        if t < 1:
            raise ValueError(
                f"experiences must be [{p}, T >= 1, ...], got rewards of shape {list(np.shape(exp.reward))}"
            )
        shapes = {"state": (p, t, cfg.state_dim), "action": (p, t, cfg.action_dim),
                  "next_state": (p, t, cfg.state_dim), "reward": (p, t), "terminal": (p, t)}  # fmt: skip
        for name, shape in shapes.items():
            if np.shape(getattr(exp, name)) != shape:
                raise ValueError(f"experiences' {name}: expected shape {list(shape)}, got "
                                 f"{list(np.shape(getattr(exp, name)))}")  # fmt: skip
        # Next states at terminals too: the update computes with them (the buffer stores them zeroed).
        finite = all(np.isfinite(a).all() for a in (exp.state, exp.action, exp.next_state))
        finite = finite and bool((np.abs(exp.reward) <= MAX_REWARD).all())  # NaN fails
        if not finite:
            raise ValueError(f"experiences to think on must be finite, with rewards within +-{MAX_REWARD:g}")

    # ------------------------------------------------------------------ weights
    def reset_weights(self, which: BoolArray) -> None:
        """Fresh small random weights for the learners `which`; their experiences are kept."""
        idx = np.flatnonzero(which)
        if idx.size:
            reinit(self.params, self.config, self._weights_rng, idx)
            self.resets[idx] += 1

    def experienced(self, n: int) -> None:
        """Count n experiences produced before this process (the thesis' learner has no use for it)."""

    def rewarded(self, reward: ArrayLike) -> None:
        """Rewards met while acting on snapshots (the thesis' learner judges squashed values alike)."""

    def prepare_thinking(self, compile: bool = False) -> None:
        """Nothing to load: the compiled think comes from numba's cache at its first call."""

    def training_state(self) -> dict[str, NDArray[Any]]:
        """What training needs beyond `params` to resume: its random streams (`random_state`)."""
        return self.random_state()

    def load_training_state(self, state: dict[str, Any]) -> None:
        """Inverse of `training_state`; ValueError for anything else.

        A file saved without it (or before it was saved) leaves the streams as the seed starts them.
        """
        other = sorted(set(state) - set(RANDOM_STATE))
        if other:
            raise ValueError(f"the thesis' learner has no training state {other[:5]}")
        self.load_random_state(state)

    def random_state(self) -> dict[str, NDArray[Any]]:
        """Where the random streams stand, and the exploration noise.

        The streams: weights (after a reset), replay sampling and exploration. A learner resumed
        from them draws what this one would have drawn next, so that a run stopped and resumed
        goes on as one that never stopped.
        """
        return {
            "random_seed": np.asarray(self.config.seed, dtype=np.int64),
            "random_weights": generator_state(self._weights_rng),
            "random_replay": generator_state(self._replay_rng),
            "random_exploration": generator_state(self.explorer.rng),
            "exploration_noise": self.explorer.noise.copy(),
        }

    def load_random_state(self, state: dict[str, Any]) -> None:
        """Inverse of `random_state`, all or none of it.

        ValueError, and nothing changed, for arrays that are not such a state; where none is
        given, the streams stay as they are.
        """
        load = self.random_state_loader(state)
        if load is not None:
            load()

    def random_state_loader(self, state: dict[str, Any]) -> Callable[[], None] | None:
        """`load_random_state`'s checks now (ValueError); what it changes, to call (None: nothing).

        Streams that began from another seed than this learner's config gives (a run resumed with
        another --seed) are not taken: that seed's own streams are what the run asked for.
        """
        given = [key for key in RANDOM_STATE if key in state]
        if not given:
            return None
        if len(given) != len(RANDOM_STATE):
            raise ValueError(f"training state has part of the random state ({', '.join(given)})")
        seed = np.asarray(state["random_seed"])
        if seed.dtype.kind not in "iu" or seed.shape != ():
            raise ValueError(f"training state random_seed: {seed.dtype} {seed.shape}, not a seed")
        if int(seed) != self.config.seed:
            return None
        noise = np.asarray(state["exploration_noise"])
        shape = self.explorer.noise.shape
        # The smooth noise [P, A] or the pink noise's processes [P, K, A]: a run resumed with
        # another exploration may hold the other layout, or another K.
        layout = noise.ndim in (2, 3) and noise.shape[:1] == shape[:1] and noise.shape[-1:] == shape[-1:]
        if noise.dtype.kind != "f" or not layout or not np.isfinite(noise).all():
            p, a = shape[0], shape[-1]
            raise ValueError(f"training state exploration_noise: {noise.dtype} {noise.shape}, expected "
                             f"finite [{p}, {a}] or [{p}, K, {a}]")  # fmt: skip
        # The noise's deviation is sigma: 20 of them is no state it reaches (1e300 held the
        # actions at their limit for thousands of ticks). Such noise restarts, as at an
        # episode's start: a run resumed with a smaller sigma may hold it too.
        bound = NOISE_DEVIATIONS * self.config.exploration.sigma
        restart = noise.shape != shape or np.abs(noise).max(initial=0.0) > bound
        if noise.shape != shape and self.config.exploration.kind in ("smooth", "pink"):  # else none is held
            log.warning("training state exploration_noise is laid out as %s, this exploration's as %s "
                        "(another kind, or tau_steps): the noise restarts", noise.shape, shape)  # fmt: skip
        elif restart:
            log.warning("training state exploration_noise is beyond %g (%d times exploration.sigma): "
                        "the noise restarts", bound, NOISE_DEVIATIONS)  # fmt: skip
        streams = [(self._weights_rng, "random_weights"), (self._replay_rng, "random_replay"),
                   (self.explorer.rng, "random_exploration")]  # fmt: skip
        states = [generator_state_from(state[key], key) for _, key in streams]

        def load() -> None:
            for (rng, _), bits in zip(streams, states, strict=True):
                rng.bit_generator.state = bits
            if restart:
                self.explorer.reset()
            else:
                self.explorer.noise[...] = noise

        return load

    def snapshot(self) -> Params:
        """A copy of the current weights (safe to read while thinking continues)."""
        return self.params.copy()

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[Any]:
        """Greedy evaluation beside training: yields a copy of the weights to act on.

        `act(x, explore=False, params=...)` on that copy resets no weights on divergence, and
        afterwards what acting changed in this learner (the last valid state, which later invalid
        states fall back on, and the divergence monitor's run) is put back, so that how often a
        benchmark evaluates does not change what its learners learn.
        """
        last_valid, run = self._last_valid.copy(), self.monitor.run.copy()
        try:
            yield self.snapshot()
        finally:
            self._last_valid, self.monitor.run = last_valid, run

    def greedy_values(self, state: ArrayLike) -> FloatArray:
        """Value of the best wire (Q of the action `act` would choose) for states [N, S] -> [P, N]."""
        x = self.state_scaler.to_unit(exactly(state, (None, self.config.state_dim), "state"))
        x = np.nan_to_num(np.clip(x, -self._limit, self._limit))
        _, out = forward(self.params, np.broadcast_to(x, (self.population, *x.shape)))
        return np.asarray(split_wires(out, self.config.n_wires, self.config.action_dim)[1].max(axis=-1))

    def q_value(self, state: ArrayLike, action: ArrayLike) -> FloatArray:
        """Q(x, u) by wire fitting for one state and action per learner ([] or [P])."""
        s, single = self._rows(state, self.config.state_dim)
        a, _ = self._rows(action, self.config.action_dim)
        x = self.state_scaler.to_unit(s)
        _, out = forward(self.params, x[:, None, :])
        wire_u, wire_q = split_wires(out[:, 0], self.config.n_wires, self.config.action_dim)
        q = wirefit_q(wire_u, wire_q, self.action_scaler.to_unit(a), self.config.smoothing_c, self.config.eps)
        return q[0] if single else q
