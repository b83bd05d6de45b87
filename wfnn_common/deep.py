"""The deep wire-fitting learner behind the thesis' learner's act-learn-think interface.

    learner = DeepWFNN(LearnerConfig.for_task(task, learner="deep"))
    u = learner.act(x).action            # numpy: the best wire of critic 1 (+ exploration)
    learner.learn(x, u, x_next, r, terminal)
    learner.think()                      # thinks_per_action minibatch updates (torch)

Acting needs numpy and numba only (`deep_net`): torch is imported the first time the learner thinks, so
a robot that acts on snapshots from a think server never loads it. The first `deep.warmup`
explored actions are uniformly random. Updates (`deep_torch`) use n-step returns built at
sampling time from consecutive stored experiences. One network per learner (population 1).
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Iterator
from dataclasses import replace
from typing import Any, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wfnn_common import deep_net
from wfnn_common.config import MAX_SAVED_COUNT, MAX_SEED, LearnerConfig
from wfnn_common.deep_net import DeepParams, DeepShapes
from wfnn_common.learner import FLOAT32_MAX, MAX_REWARD, WFNN, ActResult, BoolArray, FloatArray, exactly
from wfnn_common.replay import Experiences
from wfnn_common.update import UpdateStats, squash_reward

REFERENCE_REWARD = 10.0
REFERENCE_GAMMA = 0.99
"""The reward magnitude and discount the config's divergence_threshold is for: values bounded by
REFERENCE_REWARD / (1 - REFERENCE_GAMMA); a larger bound scales it."""


class DeepWFNN(WFNN):
    """One deep wire-fitting learner (see the module docstring)."""

    def __init__(self, config: LearnerConfig, population: int = 1, params: DeepParams | None = None) -> None:
        if config.learner != "deep":
            raise ValueError(f"DeepWFNN needs a config with learner='deep', got {config.learner!r}")
        if population != 1:
            raise ValueError(f"a deep learner is one network (population 1), got {population}")
        super().__init__(config, population, params)  # type: ignore[arg-type]
        if config.deep.n_step > 1:
            self.buffer.link_successors()

    def _init_network(self, params: Any) -> None:
        """Critic 1 from `params` (critic 2 near it) or both fresh; no torch yet."""
        self.shapes = DeepShapes.of(self.config)
        self.acted = 0 if params is None else self.config.deep.warmup
        """Explored actions taken so far (the first deep.warmup are uniformly random; none with
        given weights)."""
        if params is not None and not isinstance(params, DeepParams):
            raise ValueError("a deep learner's params must be DeepParams")
        if params is not None and params.shapes != self.shapes:
            raise ValueError(f"weights for a network of {params.shapes} do not fit this config's "
                             f"{self.shapes}")  # fmt: skip
        if params is not None and not (np.abs(params.flat) <= FLOAT32_MAX).all():
            # It trains in float32: larger weights would be infinite there (NaN fails the test too).
            raise ValueError("a deep learner's weights must be finite and within float32's range")
        if params is None:
            theta = self._fresh_theta()
            params = DeepParams(theta[None, : self.shapes.n_params].copy(), self.shapes)
        else:  # critic 2 starts near critic 1, apart enough that the twins do not stay equal
            # As float32 values, as fresh weights are (`_fresh_theta`): weights given in float64
            # (a PopArt learner's in the task's units) were acted on as given, but resumed from a
            # checkpoint taken before the first update as the trainer's float32 rounding of them.
            given = params.flat[0].astype(np.float32).astype(np.float64)
            params = DeepParams(given[None].copy(), self.shapes)
            nudge = 0.01 * deep_net.init_critic(self.shapes, self._weights_rng, self.config.init_scale)
            theta = np.concatenate([given, given + nudge]).astype(np.float32).astype(np.float64)
        self.params: DeepParams = params  # type: ignore[assignment]
        self._theta0 = theta
        self._reward_scale = 0.0
        """The largest reward magnitude stored so far (what bounds the values: `_check`)."""
        self._trainer: Any = None
        # Load the compiled act now, not in a robot's first control tick (compiling it takes seconds).
        z = np.zeros(self.config.state_dim)
        pack, dims = params.act_layout
        deep_net.act_one(pack, dims, z, z, z + 1.0, 1.0)

    def _fresh_theta(self) -> FloatArray:
        """Both critics' fresh weights, as float32 values.

        The trainer holds them so: `act` before the first update, and a checkpoint taken then,
        then use the same weights.
        """
        rng, scale = self._weights_rng, self.config.init_scale
        theta = np.concatenate([deep_net.init_critic(self.shapes, rng, scale) for _ in range(2)])
        return theta.astype(np.float32).astype(np.float64)

    def _train(self) -> Any:
        """The torch trainer, made on first use."""
        if self._trainer is None:
            from wfnn_common.deep_torch import Trainer  # torch only where the learner thinks

            self._trainer = Trainer(self.config, self._theta0, self._trainer_seed())
        return self._trainer

    def _trainer_seed(self) -> int:
        """The seed of the trainer's generator (the smoothing noise), from the weights' stream."""
        return int(self._weights_rng.integers(1 << 62))

    def _sync(self) -> None:
        """Critic 1's trained weights become `params` (the weights `act` reads)."""
        self.params = DeepParams(self._train().critic1()[None], self.shapes)

    # ------------------------------------------------------------------ act
    def _greedy(self, params: Any, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        return deep_net.greedy(params, x)

    def _act_one(self, s: FloatArray, explore: bool, params: Any) -> ActResult:
        """`act` for one state [S]: the robot's hot path, the network in one compiled kernel."""
        scaler = self.state_scaler
        pack, dims = params.act_layout
        valid, x, wire_u, wire_q, best = deep_net.act_one(pack, dims, s, scaler.mid, scaler.half, self._limit)
        if valid:
            self._last_valid = x[None]
        else:  # act on the best estimate: already scaled, so through an identity scaling
            x = self._best_estimate(x[None], np.zeros(1, dtype=np.bool_))[0]
            identity = np.zeros(x.shape[0]), np.ones(x.shape[0])
            _, _, wire_u, wire_q, best = deep_net.act_one(pack, dims, x, *identity, np.inf)
        return self._finish_one(wire_u[best], float(wire_q[best]), valid, explore, params)

    def _check(
        self, s: FloatArray, a: FloatArray, sn: FloatArray, r: FloatArray, term: BoolArray, ok: BoolArray
    ) -> tuple[Experiences, BoolArray]:
        """The thesis' learner's checks; and the divergence threshold follows the values' bound.

        Unsquashed rewards bound the values by max |r| / (1 - gamma): the config's threshold
        (1e4) is for rewards of at most REFERENCE_REWARD a step at gamma REFERENCE_GAMMA, and a
        task paying 1,000 a step, or a discount nearer 1, would look diverged at every act. The
        threshold is scaled by the bound over the reference's where that is above 1 (so tasks with
        small rewards at the usual discounts are as before).
        """
        exp, ok = super()._check(s, a, sn, r, term, ok)
        self.rewarded(r[ok])
        return exp, ok

    def rewarded(self, reward: ArrayLike) -> None:
        """Rewards [N] met: the divergence threshold follows the largest (as `learn` does).

        A robot acting on a server's snapshots learns nothing itself: without them, its
        threshold stayed the config's while the server's grew, and it judged healthy weights
        diverged and stopped following them.
        """
        r = np.abs(np.asarray(reward, dtype=np.float64).reshape(-1))
        r = r[r <= MAX_REWARD]  # NaN fails: what learn would refuse says nothing of the values
        if not r.size:
            return
        scale = float(r.max())
        if scale > self._reward_scale:
            self._reward_scale = scale
            horizon = (1.0 - REFERENCE_GAMMA) / (1.0 - self.config.gamma)  # 1 at the reference
            factor = max(1.0, scale / REFERENCE_REWARD * horizon)
            base = self.config.divergence_threshold  # a threshold at or below 0 is the user's, as set
            self.monitor.threshold = base * factor if base > 0.0 else base

    def experienced(self, n: int) -> None:
        """Count n experiences produced before this process (a robot's journal): warm-up included."""
        self.acted = max(self.acted, n)

    def prepare_thinking(self, compile: bool = False) -> None:
        """Import torch and build the trainer now, as the first think would.

        With `compile`, where deep.compile is set, the update is compiled now too (`Trainer.warm`).
        Importing torch in a thread while others run costs many times its single-threaded time on a
        busy machine (each handover of the interpreter lock waits for the scheduler), and it holds
        that lock for long stretches, so a caller with a loop to keep does it before starting threads.
        """
        trainer = self._train()
        if compile:
            trainer.warm()

    def _explore(self, greedy: FloatArray) -> FloatArray:
        self.acted += 1
        if self.acted <= self.config.deep.warmup:
            return self.explorer.rng.uniform(-1.0, 1.0, size=greedy.shape)
        return self.explorer(greedy)

    # ------------------------------------------------------------------ think
    def _n_step(self, idx: NDArray[np.int64]) -> dict[str, FloatArray]:
        """Minibatch arrays at buffer indices idx [B], with n-step returns where the data allow.

        The return follows each experience's stored successor (the experience stored later that
        starts exactly from its next state: `ReplayBuffer.link_successors`), whichever client
        sent it and however the clients' experiences and mirrored images were interleaved; it
        stops at a terminal, or where no successor is stored.
        """
        cfg, buf = self.config, self.buffer
        gamma = cfg.gamma
        state, action, next_state, raw_reward, flags = buf.take(0, idx)  # whole rows, in one gather
        reward = self._reward(raw_reward)
        terminal = flags != 0.0
        discount = np.where(terminal, 0.0, gamma)
        if cfg.deep.n_step > 1:
            now, going = idx, ~terminal
            for k in range(1, cfg.deep.n_step):
                now, found = buf.continuation(0, now)
                going = going & found
                if not going.any():
                    break
                later = buf.take(0, now)  # rows where the return stops are masked out below
                reward = reward + np.where(going, gamma**k * self._reward(later.reward), 0.0)
                term_j = later.terminal != 0.0
                next_state = np.where(going[:, None], later.next_state, next_state)
                discount = np.where(going, np.where(term_j, 0.0, gamma ** (k + 1)), discount)
                going = going & ~term_j
        return {"state": state, "action": action, "reward": reward, "next_state": next_state,
                "discount": discount}  # fmt: skip

    def _reward(self, raw: FloatArray) -> FloatArray:
        return squash_reward(raw, self.config.gamma) if self.config.squash_reward else raw

    def think(self, n: int | None = None) -> UpdateStats:
        """N minibatch updates (default thinks_per_action); nothing before the first experience."""
        cfg = self.config
        n = cfg.thinks_per_action if n is None else n
        if n <= 0 or self.buffer.count[0] == 0:
            return self.last_think
        trainer = self._train()
        q = td = 0.0
        for i in range(n):  # sampled per update: n x batch_size indices at once could be large
            rows = self.buffer.sample_indices(self._replay_rng, cfg.batch_size)[0]
            q, td = trainer.update(self._n_step(rows), stats=i == n - 1)  # only the last one's are shown
        return self._thought(n, q, td)

    def _thought(self, n: int, q: float, td: float) -> UpdateStats:
        """Count n updates done, show `act` the new weights; -> the last update's stats."""
        self.thinks += n
        self._sync()
        self.last_think = UpdateStats(np.array([q]), np.array([td]))
        return self.last_think

    def think_on(self, exp: Experiences, active: BoolArray | None = None, params: Any = None) -> UpdateStats:
        """One update on given experiences [1, T, ...] (one-step returns)."""
        if params is not None:
            raise ValueError("a deep learner thinks on its own weights only")
        if active is not None and not active[0]:
            return self.last_think
        self._check_given(exp)
        terminal = np.asarray(exp.terminal[0]) != 0
        discount = np.where(terminal, 0.0, self.config.gamma)
        batch = {"state": exp.state[0], "action": exp.action[0], "reward": self._reward(exp.reward[0]),
                 "next_state": exp.next_state[0], "discount": discount}  # fmt: skip
        return self._thought(1, *self._train().update(batch))

    # ------------------------------------------------------------------ weights
    def reset_weights(self, which: BoolArray) -> None:
        """Fresh weights for both critics and their targets, Adam restarted; experiences kept."""
        if not np.asarray(which).any():
            return
        theta = self._fresh_theta()
        if self._trainer is None:
            self._theta0 = theta
            self.params = DeepParams(theta[None, : self.shapes.n_params].copy(), self.shapes)
        else:
            self._trainer.reset(theta)
            self._sync()
        self.resets += 1

    def training_state(self) -> dict[str, NDArray[Any]]:
        """Weights of both critics, their targets and Adam's state, to save with a checkpoint.

        And the largest reward met, which sizes the divergence threshold (`rewarded`): without
        it, a learner resumed on a task of large rewards judged its own healthy weights diverged.
        And the explored actions taken (`acted`), where there were any: a learner resumed in its
        warm-up takes the rest of it. One that never acted (a think server's) leaves it out, and a
        learner resumed from it counts its warm-up as done, as one made from weights alone does.
        """
        state: dict[str, NDArray[Any]]
        if self._trainer is None:
            state = {"theta": self._theta0.astype(np.float32), "target": self._theta0.astype(np.float32)}
        else:
            state = dict(self._trainer.state())
        if self.acted > 0:
            state["acted"] = np.asarray(self.acted, dtype=np.int64)
        state.update(self.random_state())
        return {**state, "reward_scale": np.asarray(self._reward_scale, dtype=np.float64)}

    def random_state(self) -> dict[str, NDArray[Any]]:
        """The base's random streams and, once it trains, its trainer's (`random_noise`)."""
        out = super().random_state()
        if self._trainer is not None:
            out["random_noise"] = self._trainer.generator_state()
        return out

    def load_training_state(self, state: dict[str, Any]) -> None:
        """Resume from `training_state`'s arrays; ValueError if they do not fit this config.

        The arrays train in float32, so each must be real, finite and within float32's range (a
        larger finite float64 would become infinite there), and critic 1 of `theta` must be the
        weights this learner was made with (the `params` saved beside it, which `act` reads).
        """
        n = 2 * self.shapes.n_params
        arrays: dict[str, FloatArray] = {}
        for key in ("theta", "target", "adam_m", "adam_v"):
            if key in state:
                arr = np.asarray(state[key])
                if arr.dtype.kind not in "fiu" or arr.shape != (n,):
                    raise ValueError(f"training state {key}: {arr.dtype} {arr.shape}, expected real ({n},)")
                arrays[key] = arr = arr.astype(np.float64)
                if not (np.abs(arr) <= FLOAT32_MAX).all():  # NaN fails the comparison too
                    raise ValueError(f"training state {key}: not finite, or beyond float32's range")
        if not state:  # weights only (saved without their training): Adam starts afresh
            return
        if "theta" not in state or "target" not in state:
            raise ValueError("training state lacks theta or target")
        if ("adam_m" in state) != ("adam_v" in state) or ("adam_m" in state) != ("adam_step" in state):
            raise ValueError("training state has part of Adam's state")
        if "adam_v" in arrays and (arrays["adam_v"] < 0).any():
            raise ValueError("training state adam_v has negative entries")
        scale = np.asarray(state.get("reward_scale", 0.0))  # absent from checkpoints made before it
        if scale.dtype.kind not in "fiu" or scale.shape != () or not 0.0 <= float(scale) <= MAX_REWARD:
            raise ValueError(f"training state reward_scale is not a reward's size: {str(scale)[:40]!r}")
        trained = False
        if "adam_step" in state:
            step = np.asarray(state["adam_step"])
            if (
                step.dtype.kind not in "fiu"
                or step.shape != ()
                or not 0 <= float(step) <= MAX_SAVED_COUNT
                or step != np.round(step)
            ):
                raise ValueError(f"training state adam_step is not a count: {str(step)[:40]!r}")
            trained = float(step) > 0
        # Absent where the learner never acted (a think server's, and checkpoints made before it was
        # saved): its warm-up is done if it trained (as for weights alone), and not if it never did,
        # whose weights are as fresh as a new learner's (a robot's brain that never drove).
        acted = np.asarray(state.get("acted", self.acted if trained else 0))
        if acted.dtype.kind not in "iu" or acted.shape != () or not 0 <= int(acted) <= MAX_SAVED_COUNT:
            raise ValueError(f"training state acted is not a count: {str(acted)[:40]!r}")
        moments = np.zeros(3)
        if "value_moments" in state:  # saved where the values were learnt normalised (deep.popart_rate)
            moments = np.asarray(state["value_moments"])
            if (
                moments.dtype.kind not in "fiu"
                or moments.shape != (3,)
                or not np.isfinite(moments).all()
                or not 0.0 < float(moments[2]) <= 1.0
                or float(moments[1]) < 0.0
                or abs(float(moments[0])) > FLOAT32_MAX  # a mean it trains with in float32
                or float(moments[1]) > FLOAT32_MAX**2
            ):
                raise ValueError(
                    f"training state value_moments are not targets' moments: {str(moments)[:60]!r}"
                )
            moments = moments.astype(np.float64)
            state = {**state, "value_moments": moments}
        critic1 = arrays["theta"][: self.shapes.n_params]
        if moments[2] > 0.0:  # `act`'s weights give the values in the task's units
            critic1 = deep_net.in_task_units(critic1, self.shapes, *deep_net.value_scale(moments))
        if not np.array_equal(critic1.astype(np.float32), self.params.flat[0].astype(np.float32)):
            raise ValueError("training state theta: critic 1 is not the weights saved beside it")
        load_random = self.random_state_loader(state)  # checked before anything changes
        if load_random is not None and trained and "random_noise" not in state:
            # Only a state saved before the first update lacks it (the trainer is then seeded).
            raise ValueError("training state random_noise: missing, though the learner had trained")
        noise = None
        if "random_noise" in state:  # checked before anything changes, as the rest is
            from wfnn_common.deep_torch import checked_generator_state

            noise = checked_generator_state(state["random_noise"], self.config.deep.device)
        state = {**state, **arrays}
        self._theta0 = np.asarray(state["theta"], dtype=np.float64)
        trainer = self._train()
        trainer.load(state)
        if load_random is not None:
            # After the trainer is made: making it draws its seed from the weights' stream, which
            # the saved learner had done before it saved that stream's state, where it had trained.
            load_random()
            if noise is not None:
                trainer.generator.set_state(noise)
            elif "random_noise" not in state:  # saved before its first update: seeded as it would be
                trainer.generator.manual_seed(self._trainer_seed())
            # (another device type's: the trainer keeps the seed it was made with, and the restored
            # weights' stream stays where it was saved)
        self._sync()
        self.rewarded([float(scale)])
        self.acted = int(acted)

    # ------------------------------------------------------------------ views
    def greedy_values(self, state: Any) -> FloatArray:
        """Value of the best wire for states [N, S] -> [1, N]."""
        x = self.state_scaler.to_unit(exactly(state, (None, self.config.state_dim), "state"))
        x = np.nan_to_num(np.clip(x, -self._limit, self._limit))
        return deep_net.greedy(self.params, x)[1][None]

    def q_value(self, state: Any, action: Any) -> Any:
        """Q(x, u) by wire fitting with normalised smoothing ([] for one state and action)."""
        s, single = self._rows(state, self.config.state_dim)
        a, _ = self._rows(action, self.config.action_dim)
        wire_u, wire_q = deep_net.wires(self.params, self.state_scaler.to_unit(s))
        cfg = self.config
        u = self.action_scaler.to_unit(a)
        q = deep_net.wirefit_normalised(wire_u, wire_q, u, cfg.smoothing_c, cfg.eps, cfg.deep.top_k)
        return q[0] if single else q


class PopulationParams:
    """The weights of each member of a `DeepPopulation` (what its `act` takes as `params`)."""

    def __init__(self, members: list[DeepParams]) -> None:
        self.members = members
        self.flat = np.concatenate([m.flat for m in members])
        """All members' weights [P, n_params] (a copy: for saving)."""

    @property
    def population(self) -> int:
        """Number of members."""
        return len(self.members)

    def copy(self) -> PopulationParams:
        """Deep copy."""
        return PopulationParams([m.copy() for m in self.members])


class _Counts:
    """The members' replay buffers seen as one population's (`count`, `added`, `contents`)."""

    def __init__(self, members: list[DeepWFNN]) -> None:
        self._members = members

    @property
    def count(self) -> NDArray[np.int64]:
        """Stored experiences per member [P]."""
        return np.array([int(m.buffer.count[0]) for m in self._members])

    @property
    def added(self) -> NDArray[np.int64]:
        """Experiences ever added per member [P]."""
        return np.array([int(m.buffer.added[0]) for m in self._members])

    def contents(self, learner: int) -> Experiences:
        """One member's stored experiences, oldest first."""
        return self._members[learner].buffer.contents(0)


class DeepPopulation:
    """P independent deep learners with a population's interface (for benchmarks of P controllers).

    Member i has the config's seed + i, wrapped past MAX_SEED to 0 (so that every seed a config
    takes makes a population, as the thesis' learner's does). Arrays in and out are [P, ...] as
    for `WFNN`.
    """

    def __init__(self, config: LearnerConfig, population: int) -> None:
        if population < 1:
            raise ValueError(f"population must be >= 1, got {population}")
        self.config = config
        self.population = population
        self.members = [DeepWFNN(replace(config, seed=(config.seed + i) % (MAX_SEED + 1)))
                        for i in range(population)]  # fmt: skip
        self.buffer = _Counts(self.members)

    def _stack(self, name: str) -> NDArray[Any]:
        return np.array([getattr(m, name)[0] for m in self.members])

    @property
    def thinks(self) -> NDArray[np.int64]:
        """Updates per member [P]."""
        return self._stack("thinks")

    @property
    def resets(self) -> NDArray[np.int64]:
        """Divergence resets per member [P]."""
        return self._stack("resets")

    @property
    def rejected(self) -> NDArray[np.int64]:
        """Experiences refused by the sanity limits per member [P]."""
        return self._stack("rejected")

    @property
    def params(self) -> PopulationParams:
        """The members' current weights, as new objects over the same (immutable) arrays.

        Acting on them is acting on given weights, which a divergence does not reset; they are
        the weights of now (learning makes new ones).
        """
        return PopulationParams([copy.copy(cast(DeepParams, m.params)) for m in self.members])

    def snapshot(self) -> PopulationParams:
        """Copies of the members' weights."""
        return PopulationParams([cast(DeepParams, m.snapshot()) for m in self.members])

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[PopulationParams]:
        """`WFNN.evaluating` for every member: copies of their weights, their acting undone after."""
        with contextlib.ExitStack() as stack:
            yield PopulationParams([stack.enter_context(m.evaluating()) for m in self.members])

    def _rows(self, a: Any, width: int, what: str) -> FloatArray:
        """`a` as [P, width] (a population of one: [width] too), else a ValueError naming it.

        Not reshaped into place: [S, P] states for [P, S] ones were taken as other states.
        """
        if self.population == 1 and np.shape(a) == (width,):
            a = np.asarray(a)[None]
        return cast(FloatArray, exactly(a, (self.population, width), what))

    def act(self, state: Any, explore: bool = True, params: PopulationParams | None = None) -> ActResult:
        """Each member's action for its state [P, S] -> ActResult of [P, ...] arrays."""
        s = self._rows(state, self.config.state_dim, "state")
        if params is not None and len(params.members) != self.population:
            raise ValueError(f"weights of a population of {len(params.members)} do not fit this one's "
                             f"{self.population}")  # fmt: skip
        results = [m.act(s[i], explore, None if params is None else params.members[i])
                   for i, m in enumerate(self.members)]  # fmt: skip
        return ActResult(*(np.array([getattr(r, f) for r in results]) for f in ActResult._fields))

    def learn(self, state: Any, action: Any, next_state: Any, reward: Any, terminal: Any = False,
              valid: Any = True) -> BoolArray:  # fmt: skip
        """One experience per member ([P, ...] rows); -> which stored it [P]."""
        p, cfg = self.population, self.config
        rows = [self._rows(a, width, what) for a, width, what in ((state, cfg.state_dim, "state"),
                (action, cfg.action_dim, "action"), (next_state, cfg.state_dim, "next_state"))]  # fmt: skip
        r, term, ok = (np.broadcast_to(np.asarray(v), (p,)) for v in (reward, terminal, valid))
        return np.array([bool(m.learn(rows[0][i], rows[1][i], rows[2][i], r[i], term[i], ok[i]))
                         for i, m in enumerate(self.members)])  # fmt: skip

    def learn_many(self, state: Any, action: Any, next_state: Any, reward: Any, terminal: Any) -> BoolArray:
        """A block of N experiences for every member; -> which were stored [N]."""
        stored = [m.learn_many(state, action, next_state, reward, terminal) for m in self.members]
        return stored[0]

    def think(self, n: int | None = None) -> UpdateStats:
        """Each member thinks n updates (default thinks_per_action)."""
        stats = [m.think(n) for m in self.members]
        return UpdateStats(np.concatenate([s.q for s in stats]), np.concatenate([s.td_abs for s in stats]))

    def reset_weights(self, which: BoolArray) -> None:
        """Fresh weights for the members `which`."""
        for m, w in zip(self.members, np.asarray(which), strict=True):
            m.reset_weights(np.array([w]))

    def greedy_values(self, state: Any) -> FloatArray:
        """Value of each member's best wire at states [N, S] -> [P, N]."""
        return np.concatenate([m.greedy_values(state) for m in self.members])

    def q_value(self, state: Any, action: Any) -> FloatArray:
        """Q(x, u) of each member for its own state and action ([P, S], [P, A]) -> [P]."""
        cfg = self.config
        s, a = self._rows(state, cfg.state_dim, "state"), self._rows(action, cfg.action_dim, "action")
        return np.array([float(m.q_value(s[i], a[i])) for i, m in enumerate(self.members)])
