"""The Nomad 200's learned behaviours (thesis Sections 6.4-6.5) on the MuJoCo model.

`servo` (learned visual servoing, Fig 6.10): the state is the tracked target's pixel error to
the goal position (x, y), its pixel velocity (dx, dy, from two 30 Hz frames) and the robot's
translational and rotational velocity as its encoders measure them (t, r); the action is the
desired translational and rotational velocity (T, R); the reward is -|pixel error| (moving the
target to the goal), -(T^2 + R^2) (saving energy) and -((T - t)^2 + (R - r)^2) (smooth motion).
Episodes place a ball somewhere in view (the experimenter's job); while the target is lost the
state is invalid (nothing is learned), and after a second lost the ball is placed again.

`wander` (learned wandering, Fig 6.8): the state is the filtered 5 x 7 carpet match matrix and
(t, r); the action (T, R); the reward -sum(C * row) (carpet in view, nearer rows weighing
more), +t (moving forward) and the smooth-motion penalty. The robot wanders on across episodes.

Actions come at 10 Hz; the low-level controller ramps each velocity at its acceleration limit.
Encoders report the base's velocity with noise and, rarely, a wild value (Section 6.7.1): the
learner's sanity limits keep such states out of learning. The infrared ring is not in the
state: it is what the robot's veto (`NomadVec.veto`, `sims.nomad.behaviours.ir_veto`) looks at.

Here: the physics (the base driven at 10 Hz) and the behaviours' states. `NomadVec` owns the
room (`sims.nomad.world`: placing the robot, balls and targets, the walking person), the senses
(`sims.nomad.sensing`: encoders, infrared ring, carpet matrix, tracker) and the rewards
(`sims.nomad.rewards`); `NomadConfig` (`sims.nomad.config`) configures them all.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.base import TaskEnv, Transition, actions
from sims.nomad.behaviours import ir_veto
from sims.nomad.config import Behaviour, NomadConfig
from sims.nomad.model import NomadModelConfig, NomadParts, nomad_mjcf
from sims.nomad.rewards import Rewards
from sims.nomad.sensing import Sensing
from sims.nomad.vision import COLS, ROWS, NomadCamera, TargetTracker
from sims.nomad.world import World

if TYPE_CHECKING:
    from sims.render import RgbImage

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


class NomadVec:
    """n simulated Nomads, each in its own arena, advanced together."""

    def __init__(self, n: int, config: NomadConfig | None = None, seed: int = 0) -> None:
        cfg = config or NomadConfig()
        self.n = n
        self.config = cfg
        self.model_config = NomadModelConfig(
            timestep=1.0 / (cfg.rate_hz * cfg.substeps), camera_yaw_deg=cfg.camera_yaw_deg,
            image_size=(cfg.vision.width, cfg.vision.height), balls=cfg.balls,
        )  # fmt: skip
        self.model = mujoco.MjModel.from_xml_string(nomad_mjcf(self.model_config))
        self.data = [mujoco.MjData(self.model) for _ in range(n)]
        self.parts = NomadParts.find(self.model, cfg.balls)
        self._rng = np.random.default_rng(seed)
        """The generator of the episodes' draws and the senses' noise (`reset`, `new_targets`)."""
        self.command = np.zeros((n, 2))
        """Last commanded (T, R)."""
        self.setpoint = np.zeros((n, 2))
        """The low-level controller's velocity setpoint: where its ramp toward the command has
        got to (several actions at the acceleration limit)."""
        self.time = np.zeros(n)
        self.distance = np.zeros(n)
        """Metres travelled."""
        self.sensing = Sensing(self.model, self.data, self.parts, cfg, self.model_config, self._rng)
        self.world = World(self.model, self.data, self.parts, cfg, self.model_config, self.sensing, self.time)
        self.rewards = Rewards(cfg)

    # ------------------------------------------------------------------ what the parts report
    @property
    def ball_geoms(self) -> list[int]:
        """The balls' geoms, in order."""
        return self.parts.ball_geoms

    @property
    def camera(self) -> NomadCamera:
        """The robots' camera model."""
        return self.sensing.camera

    @property
    def trackers(self) -> list[TargetTracker]:
        """Each robot's target tracker."""
        return self.sensing.trackers

    @property
    def measured(self) -> FloatArray:
        """The encoders' (t, r) this tick (possibly wild) [n, 2]."""
        return self.sensing.measured

    @property
    def ir(self) -> FloatArray:
        """The infrared readings [n, ir_sensors] (m from the robot's surface)."""
        return self.sensing.ir

    @property
    def carpet_raw(self) -> FloatArray:
        """The raw carpet mismatch (Eq 6.1) [n, ROWS, COLS]."""
        return self.sensing.carpet_raw

    @property
    def carpet(self) -> FloatArray:
        """Filtered carpet mismatch (Eq 6.2) [n, ROWS, COLS], 0 carpet .. 1 not carpet."""
        return self.sensing.carpet

    @property
    def pixels(self) -> FloatArray:
        """Tracked target's pixel error to the goal (x, y) [n, 2], NaN while none is tracked."""
        return self.sensing.pixels

    @property
    def pixel_velocity(self) -> FloatArray:
        """Tracked target's pixel velocity (px/s) [n, 2], NaN while none is tracked."""
        return self.sensing.pixel_velocity

    @property
    def collisions(self) -> NDArray[np.int64]:
        """Collisions counted [n]."""
        return self.sensing.collisions

    @property
    def placed(self) -> NDArray[np.int64]:
        """Targets placed (servo) [n]."""
        return self.world.placed

    # ------------------------------------------------------------------ declared ranges
    def max_reward_of(self, behaviour: Behaviour | None = None) -> float:
        """The largest reward a behaviour earns (None: the configured one).

        Servoing's are penalties (0 at best); wandering also pays for forward speed, up to
        `forward_weight` a step: declared 0 (the default for a task), the thesis' learner judged
        values above its threshold for rewards of at most 0 diverged, and reset its weights.
        """
        return 0.0 if (behaviour or self.config.behaviour) == "servo" else float(self.config.forward_weight)

    @property
    def max_reward(self) -> float:
        """The largest reward the configured behaviour earns (`LearnerConfig.for_task`)."""
        return self.max_reward_of()

    def state_bounds(self, behaviour: Behaviour | None = None) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Declared (low, high) ends of a behaviour's state variables (None: the configured one)."""
        cfg, v = self.config, self.config.vision
        centre: tuple[float, ...]
        half: tuple[float, ...]
        if (behaviour or cfg.behaviour) == "servo":
            # Pixel errors are measured from the goal: the image's edges lie off centre by it.
            gx, gy = v.goal_px
            pv = cfg.pixel_velocity_range
            centre = (-gx, -gy, 0.0, 0.0, 0.0, 0.0)
            half = (v.width / 2, v.height / 2, pv, pv, *cfg.max_velocity)
        else:
            centre = (0.5,) * (ROWS * COLS) + (0.0, 0.0)
            half = (0.5,) * (ROWS * COLS) + cfg.max_velocity
        pairs = list(zip(centre, half, strict=True))
        return tuple(c - h for c, h in pairs), tuple(c + h for c, h in pairs)

    @property
    def state_low(self) -> tuple[float, ...]:
        """Declared lower ends of the state variables."""
        return self.state_bounds()[0]

    @property
    def state_high(self) -> tuple[float, ...]:
        """Declared upper ends of the state variables."""
        return self.state_bounds()[1]

    @property
    def action_low(self) -> tuple[float, ...]:
        """Desired (T, R), lower ends."""
        return tuple(-v for v in self.action_high)

    @property
    def action_high(self) -> tuple[float, ...]:
        """Desired (T, R), upper ends (m/s, rad/s)."""
        return self.config.max_velocity

    # ------------------------------------------------------------------ accessors
    def pose(self) -> FloatArray:
        """Each robot's (x, y, heading) [n, 3]."""
        return np.array([self.parts.pose(d) for d in self.data])

    def velocity(self) -> FloatArray:
        """Each robot's true (forward, rotational) velocity [n, 2]."""
        return np.array([self.parts.velocity(d) for d in self.data])

    def speed(self) -> FloatArray:
        """Each robot's true ground speed [n] (m/s)."""
        v = self.parts.v
        return np.array([np.hypot(d.qvel[v[0]], d.qvel[v[1]]) for d in self.data], dtype=np.float64)

    # ------------------------------------------------------------------ episodes
    def _draw_from(self, rng: np.random.Generator) -> None:
        """Episodes' draws and the senses' noise come from `rng` from now on.

        The trackers' noise changes generator only at `reset` (`Sensing.reset`).
        """
        self._rng = self.sensing.rng = rng

    def reset(self, rng: np.random.Generator) -> FloatArray:
        """Robots at rest at free places; balls and the person placed; a servo target in view."""
        self._draw_from(rng)
        for i, data in enumerate(self.data):
            mujoco.mj_resetData(self.model, data)
            self.world.reset(i, rng)
            self.sensing.reset(i, rng)
            mujoco.mj_forward(self.model, data)
        self.command[:] = 0.0
        self.setpoint[:] = 0.0
        self.time[:] = 0.0
        for i in range(self.n):
            self.sensing.sense(i, first=True)
        return self.new_targets(rng)

    def new_targets(self, rng: np.random.Generator) -> FloatArray:
        """servo: a new target in view of each robot (a step); wander: carry on."""
        self._draw_from(rng)
        if self.config.behaviour == "servo":
            for i in range(self.n):
                self.world.place_target(i, rng)
        return self.observe()

    def scatter_balls(self, i: int, rng: np.random.Generator) -> None:
        """Put robot i's balls at random free places (not under the robot)."""
        self.world.scatter_balls(i, rng)

    def acquire(self, i: int) -> bool:
        """Run the interest operator for robot i and track the first interesting object found."""
        if not self.sensing.acquire(i):
            return False
        self.world.target_seen(i)
        return bool(self.trackers[i].active)

    def collect(self, i: int) -> None:
        """Robot i has reached its target: a ball is picked up and put somewhere else; tracking stops."""
        self.world.collect(i, self._rng)

    # ------------------------------------------------------------------ stepping
    def step(self, action: FloatArray) -> Transition:
        """One 10 Hz action: ramp toward the commanded velocities, sense, reward."""
        cfg = self.config
        action = actions(action, self.n, 2)
        limits = np.asarray(cfg.max_velocity)
        target = np.clip(action, -limits, limits)
        state = self.observe()
        before_valid = self.valid()
        before_geom = self.tracked()
        dt = self.model.opt.timestep
        steps = np.arange(1, cfg.substeps + 1)[:, None]
        reach = np.asarray(cfg.max_acceleration) * dt * steps
        frames = {round(cfg.substeps * f / 3) - 1 for f in (1, 2, 3)}  # 30 Hz frames
        moved = np.zeros(self.n, dtype=np.bool_)
        q = self.parts.q
        for i, data in enumerate(self.data):
            start = np.array([data.qpos[q[0]], data.qpos[q[1]]])
            profile = self.setpoint[i] + np.clip(target[i] - self.setpoint[i], -reach, reach)
            self.world.move_person(i)
            for k in range(cfg.substeps):
                data.ctrl[:] = (profile[k, 0], 0.0, profile[k, 1])
                mujoco.mj_step(self.model, data)
                if k in frames:
                    self.sensing.frame(i)
            self.setpoint[i] = profile[-1]
            self.time[i] += 1.0 / cfg.rate_hz
            self.distance[i] += float(np.hypot(data.qpos[q[0]] - start[0], data.qpos[q[1]] - start[1]))
            self.sensing.sense(i)
            moved[i] = self.world.replace_lost_target(i, self._rng)
        self.command = target
        next_state = self.observe()
        valid = self.valid()
        same = self.tracked() == before_geom
        learnable = before_valid & valid & ~moved & (same | (cfg.behaviour != "servo"))
        reward = self.reward(state, target, next_state)
        return Transition(next_state, reward, np.zeros(self.n, dtype=np.bool_), learnable)

    # ------------------------------------------------------------------ what the robot sees
    def interesting(self, i: int) -> list[tuple[int, FloatArray]]:
        """The interest operator on robot i's latest raw carpet matrix: [(geom, point [3])]."""
        return self.sensing.interesting(i)

    def tracked(self) -> NDArray[np.int64]:
        """The geom each robot's tracker follows [n] (-1: none)."""
        return self.sensing.tracked()

    def pixel_error(self) -> FloatArray:
        """servo: |pixel error to the goal| [n], half the image diagonal where no target is tracked."""
        return self.sensing.pixel_error()

    def camera_images(self, i: int = 0, overlay: bool = True) -> dict[str, RgbImage]:
        """What robot i's camera sees now, rendered ({"camera": [h, w, 3] uint8}), with `overlay`."""
        return self.sensing.camera_images(i, overlay)

    def close(self) -> None:
        """Release the renderers' GL contexts, if any were made."""
        self.sensing.close()

    # ------------------------------------------------------------------ state and reward
    # Both behaviours' views are kept up to date whichever behaviour is learned, so one can
    # learn from the other's actions (Section 6.6); `behaviour` None means the configured one.
    def valid(self, behaviour: Behaviour | None = None) -> BoolArray:
        """servo: a target is tracked; wander: always (the encoders are checked by the learner)."""
        if (behaviour or self.config.behaviour) == "servo":
            return np.asarray(~np.isnan(self.pixels).any(axis=1))
        return np.ones(self.n, dtype=np.bool_)

    def observe(self, behaviour: Behaviour | None = None) -> FloatArray:
        """States [n, S] (servo: pixel entries NaN while no target is tracked)."""
        if (behaviour or self.config.behaviour) == "servo":
            return np.concatenate([self.pixels, self.pixel_velocity, self.measured], axis=1)
        return np.concatenate([self.carpet.reshape(self.n, -1), self.measured], axis=1)

    def veto(self, i: int) -> Callable[[FloatArray, FloatArray], FloatArray | None]:
        """Robot i's infrared veto (`ir_veto` over its ring and its measured speed)."""
        cfg = self.config

        def speed() -> float:
            measured = float(self.measured[i, 0])
            # A wild encoder reading (Section 6.7.1) is not believed: the command stands in.
            return measured if abs(measured) <= 2 * cfg.max_translation else float(self.command[i, 0])

        return ir_veto(
            lambda: self.ir[i],
            self.sensing.ir_angles,
            speed,
            cfg.max_acceleration[0],
            self.model_config.radius,
        )

    def reward_components(
        self,
        state: FloatArray,
        action: FloatArray,
        next_state: FloatArray,
        behaviour: Behaviour | None = None,
    ) -> FloatArray:
        """Fig 6.10 (servo) or Fig 6.8 (wander) terms, signed as they add up [n, 3] (`Rewards.components`)."""
        return self.rewards.components(state, action, next_state, behaviour)

    def reward(
        self,
        state: FloatArray,
        action: FloatArray,
        next_state: FloatArray,
        behaviour: Behaviour | None = None,
    ) -> FloatArray:
        """The behaviour's reward [n] for (state, action, next_state) [n, ...]."""
        return self.rewards.total(state, action, next_state, behaviour)


class NomadEnv(TaskEnv):
    """Gymnasium Nomad: episodes of `max_steps` actions; untracked target pixels read as 0."""

    def __init__(self, config: NomadConfig | None = None, max_steps: int = 150) -> None:
        super().__init__(NomadVec(1, config), max_steps)

    def _obs(self, state: FloatArray) -> FloatArray:
        return super()._obs(np.nan_to_num(state))
