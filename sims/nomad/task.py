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
state: it is what the robot's veto (`nomad_ir_veto`) looks at.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.base import TaskEnv, Transition
from sims.nomad.behaviours import ir_veto
from sims.nomad.model import GROUP_FLOOR, GROUP_OBJECTS, GROUP_STATIC, N_BALLS, NomadModelConfig, nomad_mjcf
from sims.nomad.vision import (
    COLS,
    ROWS,
    NomadCamera,
    NomadVisionConfig,
    TargetTracker,
    Track,
    carpet_mismatch,
    interesting_cells,
    smooth_carpet,
)
from wfnn_common.config import check_fields

if TYPE_CHECKING:  # cv2 and the GL context load only when something is rendered
    from sims.hydra.render import ImageTracker
    from sims.nomad.render import CarpetGrid, FloatImage
    from sims.render import CameraRenderer, RgbImage

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Behaviour = Literal["servo", "wander"]
BEHAVIOURS: tuple[Behaviour, ...] = ("servo", "wander")
WILD_ENCODER = -299_792_458.0
"""What the thesis' encoders once reported: the speed of light, backwards (Section 6.7.1)."""
IR_BEAM_DEG = 7.5
"""Half-width of an infrared sensor's beam (degrees; 16 sensors are 22.5 degrees apart)."""
Seen = tuple[int, FloatArray, tuple[FloatArray, float] | None]
"""An interesting object: its geom, the world point seen, and (rendered vision) its pixel and
radius in the image, where its template is cut."""
PERSON_PATIENCE_S = 3.0
"""How long the walking person waits for a robot in their way before turning back."""


@dataclass(frozen=True, kw_only=True)
class NomadConfig:
    """The behaviour learned, the robot's limits, rewards and episodes."""

    behaviour: Behaviour = "servo"
    rate_hz: float = 10.0
    substeps: int = 50
    """Physics steps per action."""
    max_translation: float = 0.5
    """Largest translational velocity command (m/s), forward or backward."""
    max_rotation: float = 0.8
    """Largest rotational velocity command (rad/s)."""
    max_acceleration: tuple[float, float] = (0.5, 2.0)
    """Acceleration limits of the low-level controller (m/s^2, rad/s^2)."""
    encoder_noise: tuple[float, float] = (0.01, 0.02)
    """Standard deviation of the measured velocities (m/s, rad/s)."""
    encoder_glitch: float = 0.001
    """Probability per action that the encoders report a wild value."""
    camera_yaw_deg: float = 0.0
    """Camera turned away from the direction of travel (Fig 6.14)."""
    pixel_velocity_range: float = 400.0
    """Declared range of target pixel velocities (px/s) for the learner's scaling."""
    position_weight: float = 3.0
    """servo: penalty per half image diagonal of pixel error."""
    energy_weight: float = 0.01
    """servo: penalty weight of (T^2 + R^2), velocities in units of their limits."""
    smoothness_weight: float = 0.05
    """Penalty weight of ((T - t)^2 + (R - r)^2), velocities in units of their limits. Small:
    the base accelerates slowly, so a command differs from the measured velocity for several
    actions; with 0.5 (and energy 0.1) the servo controllers hardly drove toward far targets in
    early `wfnn-bench nomad` runs, made before the velocity ramp was corrected and not repeated
    since."""
    carpet_weight: float = 1.0
    """wander: penalty weight of the row-weighted carpet mismatch (0..1)."""
    forward_weight: float = 0.5
    """wander: reward weight of the measured forward velocity (in units of its limit)."""
    target_distance: tuple[float, float] = (0.8, 2.6)
    """servo: a new target is placed this far ahead of the camera (m)..."""
    target_bearing_deg: float = 18.0
    """...within this bearing of the camera's direction."""
    lost_reset_s: float = 1.0
    """servo: after the target has been lost this long it is placed again (not learned across)."""
    ir_sensors: int = 16
    ir_range: float = 1.0
    """Infrared readings saturate at this range (m from the robot's surface)."""
    person_speed: float = 0.4
    """The walking person's speed (m/s; 0 keeps them still)."""
    balls: int = N_BALLS
    """Balls in the arena (objects to pursue)."""
    vision: NomadVisionConfig = field(default_factory=NomadVisionConfig)

    def __post_init__(self) -> None:
        check_fields(self)
        if self.behaviour not in BEHAVIOURS:
            raise ValueError(f"behaviour must be one of {BEHAVIOURS}, got {self.behaviour!r}")
        if self.rate_hz <= 0 or self.substeps < 3:
            raise ValueError("rate_hz must be > 0 and substeps >= 3")

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the state variables, in order."""
        motion = ("t_measured", "r_measured")
        if self.behaviour == "servo":
            return ("x_error_px", "y_error_px", "x_velocity_px_s", "y_velocity_px_s", *motion)
        return tuple(f"carpet_{r}_{c}" for r in range(ROWS) for c in range(COLS)) + motion


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
        m = self.model = mujoco.MjModel.from_xml_string(nomad_mjcf(self.model_config))
        self.data = [mujoco.MjData(m) for _ in range(n)]
        self._rng = np.random.default_rng(seed)

        def joint(name: str) -> tuple[int, int]:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            return int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j])

        self._q = [joint(j)[0] for j in ("x", "y", "yaw")]
        self._v = [joint(j)[1] for j in ("x", "y", "yaw")]
        self._balls = [joint(f"ball{k}") for k in range(cfg.balls)]
        self.ball_geoms = [
            mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"ball{k}") for k in range(cfg.balls)
        ]
        self._person = int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "person")])
        self._base_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "base")
        self._base_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "base")
        self._floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
        self._harmless = {self._floor, *self.ball_geoms}
        self.obstacles = [
            (float(m.geom_pos[g][0]), float(m.geom_pos[g][1]), 0.5)
            for g in range(m.ngeom)
            if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) in ("pot",)
            or (mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "").startswith("pillar")
        ]
        """(x, y, keep-out radius) of the fixed obstacles, for placing things."""
        self.camera = NomadCamera(m, cfg.vision, self._base_body)
        self.trackers = [TargetTracker(self.camera, self._rng) for _ in range(n)]
        angles = 2 * np.pi * np.arange(cfg.ir_sensors) / cfg.ir_sensors
        self.ir_angles = angles
        """Directions of the infrared sensors in the robot's frame (rad, 0 ahead, counter-clockwise)."""
        # Each sensor's beam is a cone: rays at its centre and +-IR_BEAM_DEG, the nearest reading
        # counts (a single ray per sensor slips past a shoe between two sensors).
        beam = (angles[:, None] + np.deg2rad([0.0, -IR_BEAM_DEG, IR_BEAM_DEG])).ravel()
        self._ir_dirs = np.stack([np.cos(beam), np.sin(beam), np.zeros_like(beam)], axis=1)
        self._ir_groups = np.ones(6, dtype=np.uint8)
        self._ir_groups[GROUP_FLOOR] = 0
        self.command = np.zeros((n, 2))
        """Last commanded (T, R)."""
        self.setpoint = np.zeros((n, 2))
        """The low-level controller's velocity setpoint: where its ramp toward the command has
        got to (several actions at the acceleration limit)."""
        self.measured = np.zeros((n, 2))
        """The encoders' (t, r) this tick (possibly wild)."""
        self.ir = np.full((n, cfg.ir_sensors), cfg.ir_range)
        self.carpet_raw = np.zeros((n, ROWS, COLS))
        self._looked: list[tuple[NDArray[np.int32], FloatArray] | None] = [None] * n
        """What each robot's grid rays met when carpet_raw was computed (geoms, points)."""
        self._difference: list[FloatImage | None] = [None] * n
        """Rendered vision: the per-pixel carpet difference carpet_raw was computed from."""
        self.carpet = np.zeros((n, ROWS, COLS))
        """Filtered carpet mismatch (Eq 6.2), 0 carpet .. 1 not carpet."""
        self.pixels = np.full((n, 2), np.nan)
        """Tracked target's pixel error to the goal (x, y), NaN while none is tracked."""
        self.pixel_velocity = np.full((n, 2), np.nan)
        self._last_frame = np.full((n, 2), np.nan)
        self.time = np.zeros(n)
        self._person_walked = np.zeros(n)
        """Metres the person has walked (they wait while a robot is in their way)."""
        self._person_waited = np.zeros(n)
        self._lost_since = np.zeros(n)
        self.collisions = np.zeros(n, dtype=np.int64)
        self._touching = np.zeros(n, dtype=np.bool_)
        self.distance = np.zeros(n)
        """Metres travelled."""
        self.placed = np.zeros(n, dtype=np.int64)
        """Targets placed (servo)."""
        self._renderer: CameraRenderer | None = None
        """Renders full-size pictures for a person (`camera_images`)."""
        # Rendered vision: each robot's latest frame, when (sim time) it was rendered, and where a
        # newly started target's template is to be cut (pixel, radius; image units).
        self.rendered = cfg.vision.source == "render"
        self._vision_renderer: CameraRenderer | None = None
        self._frames: list[FloatImage | None] = [None] * n
        self._frame_time = np.full(n, -1.0)
        self._cut: list[tuple[FloatArray, float] | None] = [None] * n
        self._grid: CarpetGrid | None = None
        self._image_trackers: list[ImageTracker] = []
        if self.rendered:
            from sims.hydra.render import ImageTracker
            from sims.nomad.render import CarpetGrid

            self._grid = CarpetGrid(cfg.vision)
            self._image_trackers = [ImageTracker(cfg.vision) for _ in range(n)]

    # ------------------------------------------------------------------ declared ranges
    def state_bounds(self, behaviour: Behaviour | None = None) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Declared (low, high) ends of a behaviour's state variables (None: the configured one)."""
        cfg, v = self.config, self.config.vision
        motion = (cfg.max_translation, cfg.max_rotation)
        if (behaviour or cfg.behaviour) == "servo":
            gx, gy = v.goal_px
            pv = cfg.pixel_velocity_range
            high = (v.width / 2 - gx, v.height / 2 - gy, pv, pv, *motion)
            return (-v.width / 2 - gx, -v.height / 2 - gy, -pv, -pv, *(-m for m in motion)), high
        return (0.0,) * (ROWS * COLS) + tuple(-m for m in motion), (1.0,) * (ROWS * COLS) + motion

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
        return (-self.config.max_translation, -self.config.max_rotation)

    @property
    def action_high(self) -> tuple[float, ...]:
        """Desired (T, R), upper ends (m/s, rad/s)."""
        return (self.config.max_translation, self.config.max_rotation)

    # ------------------------------------------------------------------ accessors
    def pose(self) -> FloatArray:
        """Each robot's (x, y, heading) [n, 3]."""
        return np.array([[d.qpos[q] for q in self._q] for d in self.data])

    def velocity(self) -> FloatArray:
        """Each robot's true (forward, rotational) velocity [n, 2]."""
        return np.array([self._velocity(i) for i in range(self.n)])

    def _velocity(self, i: int) -> FloatArray:
        d = self.data[i]
        heading = d.qpos[self._q[2]]
        vx, vy = d.qvel[self._v[0]], d.qvel[self._v[1]]
        return np.array([vx * np.cos(heading) + vy * np.sin(heading), d.qvel[self._v[2]]])

    # ------------------------------------------------------------------ episodes
    def reset(self, rng: np.random.Generator) -> FloatArray:
        """Robots at rest at free places; balls and the person placed; a servo target in view."""
        self._rng = rng
        for i, data in enumerate(self.data):
            mujoco.mj_resetData(self.model, data)
            x, y = self._free_spot(rng, 0.8)
            data.qpos[self._q] = (x, y, rng.uniform(-np.pi, np.pi))
            self.scatter_balls(i, rng)
            self.trackers[i].rng = rng
            self.trackers[i].stop()
            self._frame_time[i] = -1.0
            mujoco.mj_forward(self.model, data)
        self.command[:] = 0.0
        self.setpoint[:] = 0.0
        self.measured[:] = 0.0
        self.carpet[:] = 0.0
        self.time[:] = 0.0
        self._person_walked[:] = 0.0
        self._person_waited[:] = 0.0
        self._touching[:] = False
        for i in range(self.n):
            self._sense(i, first=True)
        return self.new_targets(rng)

    def new_targets(self, rng: np.random.Generator) -> FloatArray:
        """servo: a new target in view of each robot (a step); wander: carry on."""
        self._rng = rng
        if self.config.behaviour == "servo":
            for i in range(self.n):
                self._place_target(i)
        return self.observe()

    def _free_spot(self, rng: np.random.Generator, clearance: float) -> tuple[float, float]:
        ax, ay = (s / 2 - clearance for s in self.model_config.arena)
        for _ in range(1000):
            x, y = rng.uniform(-ax, ax), rng.uniform(-ay, ay)
            if all(np.hypot(x - ox, y - oy) > r + clearance for ox, oy, r in self.obstacles):
                return float(x), float(y)
        raise RuntimeError("no free spot in the arena")

    def _spot_away(self, i: int, rng: np.random.Generator, distance: float) -> tuple[float, float]:
        """A free place for a ball, at least `distance` from robot i's centre (100 tries)."""
        robot = self.data[i].qpos[self._q[:2]]
        for _ in range(100):
            xy = self._free_spot(rng, 0.4)
            if np.hypot(xy[0] - robot[0], xy[1] - robot[1]) > distance:
                break
        return xy

    def scatter_balls(self, i: int, rng: np.random.Generator) -> None:
        """Put robot i's balls at random free places (not under the robot)."""
        for k in range(len(self._balls)):
            self._put_ball(i, k, self._spot_away(i, rng, self.model_config.radius + 0.3))

    def _put_ball(self, i: int, k: int, xy: tuple[float, float]) -> None:
        q, v = self._balls[k]
        data = self.data[i]
        data.qpos[q : q + 7] = (xy[0], xy[1], self.model_config.ball_radius, 1, 0, 0, 0)
        data.qvel[v : v + 6] = 0.0
        self._frame_time[i] = -1.0  # the scene changed: a rendered frame is out of date

    def _place_target(self, i: int) -> None:
        """Put a ball in view ahead of the camera and start tracking it.

        As the interest operator would pick an isolated ball; the other balls go out of the way.
        """
        cfg, rng, data = self.config, self._rng, self.data[i]
        x, y, heading = (data.qpos[q] for q in self._q)
        look = heading + np.deg2rad(cfg.camera_yaw_deg)
        k = int(rng.integers(len(self._balls)))
        for _ in range(100):
            dist = rng.uniform(*cfg.target_distance) + self.model_config.camera_forward
            bearing = look + np.deg2rad(rng.uniform(-cfg.target_bearing_deg, cfg.target_bearing_deg))
            bx, by = x + dist * np.cos(bearing), y + dist * np.sin(bearing)
            ax, ay = (s / 2 - 0.3 for s in self.model_config.arena)
            if (
                abs(bx) < ax
                and abs(by) < ay
                and all(np.hypot(bx - ox, by - oy) > r for ox, oy, r in self.obstacles)
            ):
                break
        else:  # nowhere in view: turn the robot round and try again next time
            data.qpos[self._q[2]] += np.pi
        for other in range(len(self._balls)):
            if other != k:
                self._put_ball(i, other, self._free_spot(rng, 0.4))
        self._put_ball(i, k, (bx, by))
        mujoco.mj_forward(self.model, data)
        tracker = self.trackers[i]
        geom = self.ball_geoms[k]
        tracker.start(data, geom, data.geom_xpos[geom].copy())
        if self.rendered:
            pixel, depth = self.camera.project(data, data.geom_xpos[geom])
            self._cut[i] = (pixel, self.model_config.ball_radius * self.camera.focal / max(depth, 1e-6))
        self.placed[i] += 1
        self._last_frame[i] = np.nan
        self._frame(i)
        self._lost_since[i] = self.time[i]

    # ------------------------------------------------------------------ stepping
    def step(self, action: FloatArray) -> Transition:
        """One 10 Hz action: ramp toward the commanded velocities, sense, reward."""
        cfg = self.config
        action = np.asarray(action, dtype=np.float64).reshape(self.n, 2)
        limits = np.array([cfg.max_translation, cfg.max_rotation])
        target = np.clip(action, -limits, limits)
        state = self.observe()
        before_valid = self.valid()
        before_geom = np.array([t.geom for t in self.trackers])
        dt = self.model.opt.timestep
        steps = np.arange(1, cfg.substeps + 1)[:, None]
        reach = np.asarray(cfg.max_acceleration) * dt * steps
        frames = {round(cfg.substeps * f / 3) - 1 for f in (1, 2, 3)}  # 30 Hz frames
        moved = np.zeros(self.n, dtype=np.bool_)
        for i, data in enumerate(self.data):
            start = np.array([data.qpos[self._q[0]], data.qpos[self._q[1]]])
            profile = self.setpoint[i] + np.clip(target[i] - self.setpoint[i], -reach, reach)
            self._move_person(i)
            for k in range(cfg.substeps):
                data.ctrl[:] = (profile[k, 0], 0.0, profile[k, 1])
                mujoco.mj_step(self.model, data)
                if k in frames:
                    self._frame(i)
            self.setpoint[i] = profile[-1]
            self.time[i] += 1.0 / cfg.rate_hz
            self.distance[i] += float(
                np.hypot(data.qpos[self._q[0]] - start[0], data.qpos[self._q[1]] - start[1])
            )
            self._sense(i)
            moved[i] = self._replace_lost_target(i)
        self.command = target
        next_state = self.observe()
        valid = self.valid()
        same = np.array([t.geom for t in self.trackers]) == before_geom
        learnable = before_valid & valid & ~moved & (same | (cfg.behaviour != "servo"))
        reward = self.reward(state, target, next_state)
        return Transition(next_state, reward, np.zeros(self.n, dtype=np.bool_), learnable)

    def _move_person(self, i: int) -> None:
        """The person walks to and fro along the south wall, waiting while the robot is in the way."""
        cfg = self.config
        if cfg.person_speed <= 0:
            return
        ax, ay = (s / 2 for s in self.model_config.arena)
        span = 2 * (ax - 1.0)
        phase = self._person_walked[i] % (2 * span)
        along = phase if phase < span else 2 * span - phase
        heading = 1.0 if phase < span else -1.0
        x, y = -(ax - 1.0) + along, -ay + 0.6
        data = self.data[i]
        # People wait for a robot in their way, and go back the way they came after a while; they
        # do not walk into it.
        ahead = (data.qpos[self._q[0]] - x) * heading
        if -0.2 < ahead < 0.3 + self.model_config.radius + 0.5 and abs(data.qpos[self._q[1]] - y) < 0.7:
            self._person_waited[i] += 1.0 / cfg.rate_hz
            if self._person_waited[i] >= PERSON_PATIENCE_S:
                self._person_walked[i] = 2 * span - phase  # the same place, facing the other way
                self._person_waited[i] = 0.0
        else:
            self._person_waited[i] = 0.0
            self._person_walked[i] += cfg.person_speed / cfg.rate_hz
        data.mocap_pos[self._person] = (x, y, 0.0)
        half = 0.0 if heading > 0 else np.pi
        data.mocap_quat[self._person] = (np.cos(half / 2), 0.0, 0.0, np.sin(half / 2))

    def _frame(self, i: int) -> None:
        """One 30 Hz camera frame: the tracker; pixel error to the goal and pixel velocity."""
        data = self.data[i]
        mujoco.mj_camlight(self.model, data)
        track = self._track_image(i) if self.rendered else self.trackers[i].observe(self.model, data)
        if track.found:
            error = track.pixel - np.asarray(self.config.vision.goal_px)
            last = self._last_frame[i]
            self.pixel_velocity[i] = 0.0 if np.isnan(last).any() else (error - last) * 30.0
            self.pixels[i] = error
            self._last_frame[i] = error
        else:
            self.pixels[i] = np.nan
            self.pixel_velocity[i] = np.nan
            self._last_frame[i] = np.nan

    def _vision_frame(self, i: int) -> FloatImage:
        """Robot i's camera frame now, rendered: colours 0..1 at the rendered size.

        One render per physics state; the first call acquires the carpet templates.
        """
        from sims.nomad.render import to_colour

        data, v = self.data[i], self.config.vision
        if self._frame_time[i] == data.time and (frame := self._frames[i]) is not None:
            return frame
        assert self._grid is not None
        if self._vision_renderer is None:
            from sims.render import CameraRenderer

            self._vision_renderer = CameraRenderer(self.model, *self._grid.size)
        if self._grid.template is None:
            self._grid.acquire(to_colour(self._carpet_view(), v.image_noise, self._rng))
        frame = to_colour(self._vision_renderer.rgb(data, "camera"), v.image_noise, self._rng)
        self._frames[i], self._frame_time[i] = frame, data.time
        return frame

    def _carpet_view(self) -> RgbImage:
        """Start-up: the camera's view of open carpet from the middle of the room.

        The room's furniture, balls and the person are left out, as if the experimenter had
        cleared the view.
        """
        assert self._vision_renderer is not None
        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        return self._vision_renderer.rgb(data, "camera", hidden_groups=(GROUP_STATIC, GROUP_OBJECTS))

    def _track_image(self, i: int) -> Track:
        """One rendered frame of robot i's tracker.

        Template matching around the target's last position; a target not found there is lost
        (and forgotten).
        """
        tracker, image_tracker = self.trackers[i], self._image_trackers[i]
        if not tracker.active:
            image_tracker.reset()
            return Track(False, np.zeros(2))
        frame = self._vision_frame(i)
        cut, self._cut[i] = self._cut[i], None
        if cut is not None and not image_tracker.acquire(frame, cut[0], cut[1], follow=True):
            tracker.stop()  # nothing to cut a template from (out of view, or too plain)
            return Track(False, np.zeros(2))
        measured = image_tracker.observe(frame)
        if not measured.found or measured.switched:
            tracker.stop()
            image_tracker.reset()
            return Track(False, np.zeros(2))
        return Track(True, measured.pixel)

    def _sense(self, i: int, first: bool = False) -> None:
        """Encoders, infrared ring, carpet matrix and collisions at the end of an action."""
        cfg, data, rng = self.config, self.data[i], self._rng
        true = self._velocity(i) if not first else np.zeros(2)
        self.measured[i] = true + rng.normal(0.0, cfg.encoder_noise)
        if rng.random() < cfg.encoder_glitch:
            self.measured[i, 0] = WILD_ENCODER
        heading = data.qpos[self._q[2]]
        rot = np.array(
            [[np.cos(heading), -np.sin(heading), 0], [np.sin(heading), np.cos(heading), 0], [0, 0, 1]]
        )
        origin = np.array([data.qpos[self._q[0]], data.qpos[self._q[1]], self.model_config.ir_height])
        dirs = self._ir_dirs @ rot.T
        rays = len(dirs)
        geoms = np.zeros(rays, dtype=np.int32)
        dist = np.zeros(rays)
        cutoff = self.model_config.radius + cfg.ir_range
        mujoco.mj_multiRay(self.model, data, origin, dirs.ravel(), self._ir_groups, 1, self._base_body,
                           geoms, dist, None, rays, cutoff)  # fmt: skip
        readings = np.where(
            dist >= 0, np.clip(dist - self.model_config.radius, 0, cfg.ir_range), cfg.ir_range
        )
        self.ir[i] = readings.reshape(cfg.ir_sensors, -1).min(axis=1)
        if self.rendered:
            assert self._grid is not None
            difference = self._difference[i] = self._grid.difference(self._vision_frame(i))
            self.carpet_raw[i] = self._grid.mismatch(difference)
        else:
            hit, points = self._looked[i] = self.camera.look(self.model, data)
            self.carpet_raw[i] = carpet_mismatch(self.model, hit, points, cfg.vision, rng)
        v = cfg.vision
        self.carpet[i] = smooth_carpet(self.carpet_raw[i], None if first else self.carpet[i], v.alpha, v.beta)
        # A collision is the base touching anything but the floor and the balls (which it may
        # nudge while pursuing them).
        touching = any(
            self._base_geom in (c.geom1, c.geom2) and not {c.geom1, c.geom2} & self._harmless
            for c in data.contact[: data.ncon]
        )
        if touching and not self._touching[i]:
            self.collisions[i] += 1
        self._touching[i] = touching

    def _replace_lost_target(self, i: int) -> bool:
        """servo: a target lost for `lost_reset_s` is placed again in view. True if so."""
        cfg = self.config
        if cfg.behaviour != "servo":
            return False
        if self.trackers[i].active:
            self._lost_since[i] = self.time[i]
            return False
        if self.time[i] - self._lost_since[i] < cfg.lost_reset_s:
            return False
        self._place_target(i)
        return True

    def interesting(self, i: int) -> list[tuple[int, FloatArray]]:
        """The interest operator on robot i's latest raw carpet matrix.

        Returns, per interesting object, the geom its rays met most and the mean point where
        they met it (where a template of it would be taken): [(geom, point [3])]. Rendered
        vision: the geom and point the ray through the object's pixel meets.
        """
        return [(geom, point) for geom, point, _ in self._objects(i)]

    def _objects(self, i: int) -> list[Seen]:
        """`interesting`, with (pixel, radius) where rendered vision saw each object."""
        if self.rendered:
            return self._rendered_objects(i)
        # The rays the carpet matrix was measured with: the object is what those cells saw.
        looked = self._looked[i]
        if looked is None:
            return []
        hit, points = looked
        out: list[Seen] = []
        for cells in interesting_cells(self.carpet_raw[i], self.config.vision):
            geoms = np.concatenate([hit[r, c] for r, c in cells])
            where = np.concatenate([points[r, c] for r, c in cells])
            chosen = geoms[(geoms >= 0) & (geoms != self._floor)]
            if chosen.size:
                geom = int(np.bincount(chosen).argmax())
                out.append((geom, where[geoms == geom].mean(axis=0), None))
        return out

    def _rendered_objects(self, i: int) -> list[Seen]:
        """Interesting objects in robot i's latest rendered frame.

        Which geom each is (what the ray through its pixel meets) only says which ball is picked
        up when it is reached.
        """
        # The image the carpet matrix was measured in: the object is what those cells saw.
        difference = self._difference[i]
        if self._grid is None or difference is None:
            return []
        out: list[Seen] = []
        for cells in interesting_cells(self.carpet_raw[i], self.config.vision):
            seen = self._grid.object_at(difference, cells)
            if seen is None:
                continue
            geom, point = self.camera.ray(self.model, self.data[i], seen[0])
            if geom >= 0 and geom != self._floor:
                out.append((geom, point, seen))
        return out

    # ------------------------------------------------------------------ pictures
    def camera_images(self, i: int = 0, overlay: bool = True) -> dict[str, RgbImage]:
        """What robot i's camera sees now, rendered ({"camera": [h, w, 3] uint8}).

        With `overlay`: the carpet grid as squares sized by the filtered mismatch (Fig 6.4),
        the goal position (green) and the tracked target (red), as in Fig 6.5.
        """
        import cv2

        from sims.render import CameraRenderer

        v = self.config.vision
        if self._renderer is None:
            self._renderer = CameraRenderer(self.model, v.width, v.height)
        image = self._renderer.rgb(self.data[i], "camera").copy()
        if overlay:
            centres = self.camera.grid.mean(axis=2) + np.array([v.width / 2, v.height / 2])
            for r in range(ROWS):
                for c in range(COLS):
                    cx, cy = (round(float(p)) for p in centres[r, c])
                    half = 2 + round(10 * float(self.carpet[i, r, c]))
                    cv2.rectangle(image, (cx - half, cy - half), (cx + half, cy + half), (255, 255, 255), 1)
            gx, gy = (round(v.width / 2 + v.goal_px[0]), round(v.height / 2 + v.goal_px[1]))
            cv2.rectangle(image, (gx - 9, gy - 9), (gx + 9, gy + 9), (40, 220, 40), 1)
            if not np.isnan(self.pixels[i]).any():
                tx, ty = (round(float(p)) for p in np.array([gx, gy]) + self.pixels[i])
                cv2.rectangle(image, (tx - 9, ty - 9), (tx + 9, ty + 9), (230, 40, 40), 2)
        return {"camera": image}

    def close(self) -> None:
        """Release the renderers' GL contexts, if any were made."""
        for renderer in (self._renderer, self._vision_renderer):
            if renderer is not None:
                renderer.close()
        self._renderer = self._vision_renderer = None

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
            lambda: self.ir[i], self.ir_angles, speed, cfg.max_acceleration[0], self.model_config.radius
        )

    def tracked(self) -> NDArray[np.int64]:
        """The geom each robot's tracker follows [n] (-1: none)."""
        return np.array([t.geom for t in self.trackers])

    def acquire(self, i: int) -> bool:
        """Run the interest operator for robot i and track the first interesting object found."""
        found = self._objects(i)
        if not found:
            return False
        geom, point, seen = found[0]
        self.trackers[i].start(self.data[i], geom, point)
        self._cut[i] = seen
        self._last_frame[i] = np.nan
        self._frame(i)
        self._lost_since[i] = self.time[i]
        return bool(self.trackers[i].active)

    def collect(self, i: int) -> None:
        """Robot i has reached its target: a ball is picked up and put somewhere else; tracking stops."""
        geom = self.trackers[i].geom
        if geom in self.ball_geoms:
            k = self.ball_geoms.index(geom)
            self._put_ball(i, k, self._spot_away(i, self._rng, 2.0))  # not straight back into view
            mujoco.mj_forward(self.model, self.data[i])
        self.trackers[i].stop()
        self.pixels[i] = self.pixel_velocity[i] = self._last_frame[i] = np.nan

    def reward_components(
        self,
        state: FloatArray,
        action: FloatArray,
        next_state: FloatArray,
        behaviour: Behaviour | None = None,
    ) -> FloatArray:
        """Fig 6.10 (servo) or Fig 6.8 (wander) terms, signed as they add up [n, 3].

        servo: (-pixel error, -energy, -roughness); wander: (-carpet mismatch, +forward,
        -roughness). `state` gives the measured (t, r) the smoothness penalty compares with.
        """
        cfg = self.config
        limits = np.array([cfg.max_translation, cfg.max_rotation])
        state, next_state = np.atleast_2d(state), np.atleast_2d(next_state)
        u = np.atleast_2d(action) / limits
        measured = np.clip(state[:, -2:], -limits, limits) / limits
        rough = -cfg.smoothness_weight * ((u - measured) ** 2).sum(axis=1)
        if (behaviour or cfg.behaviour) == "servo":
            half_diagonal = cfg.vision.half_diagonal
            error = np.hypot(*np.nan_to_num(next_state[:, :2].T, nan=half_diagonal))
            return np.stack([-cfg.position_weight * error / half_diagonal,
                             -cfg.energy_weight * (u**2).sum(axis=1), rough], axis=1)  # fmt: skip
        rows = np.arange(1, ROWS + 1, dtype=np.float64)
        carpet = next_state[:, : ROWS * COLS].reshape(-1, ROWS, COLS).mean(axis=2) @ rows / rows.sum()
        forward = np.clip(next_state[:, -2], -cfg.max_translation, cfg.max_translation) / cfg.max_translation
        return np.stack([-cfg.carpet_weight * carpet, cfg.forward_weight * forward, rough], axis=1)

    def reward(
        self,
        state: FloatArray,
        action: FloatArray,
        next_state: FloatArray,
        behaviour: Behaviour | None = None,
    ) -> FloatArray:
        """The behaviour's reward [n] for (state, action, next_state) [n, ...]."""
        return np.asarray(self.reward_components(state, action, next_state, behaviour).sum(axis=1))

    def speed(self) -> FloatArray:
        """Each robot's true ground speed [n] (m/s)."""
        out = np.zeros(self.n)
        for i, d in enumerate(self.data):
            out[i] = np.hypot(d.qvel[self._v[0]], d.qvel[self._v[1]])
        return out

    def pixel_error(self) -> FloatArray:
        """servo: |pixel error to the goal| [n], half the image diagonal where no target is tracked."""
        half_diagonal = self.config.vision.half_diagonal
        return np.where(np.isnan(self.pixels[:, 0]), half_diagonal, np.hypot(*np.nan_to_num(self.pixels).T))


class NomadEnv(TaskEnv):
    """Gymnasium Nomad: episodes of `max_steps` actions; untracked target pixels read as 0."""

    def __init__(self, config: NomadConfig | None = None, max_steps: int = 150) -> None:
        super().__init__(NomadVec(1, config), max_steps)

    def _obs(self, state: FloatArray) -> FloatArray:
        return super()._obs(np.nan_to_num(state))
