"""HyDrA visual servoing (thesis Section 7.4, Fig 7.6) on the MuJoCo model, any of 2^8 configurations.

Each included joint adds its angle and angular velocity (a copy of the last velocity command,
as HyDrA's software reports) to the state, one action (the desired angular velocity) and a
smoothness penalty -|previous command - new command|. Each included image axis (left/right
camera, x/y) adds the tracked target's pixel error and pixel velocity (from two consecutive
30 Hz frames, one frame old when acted on) and the penalties -|x| and -|dx|. Actions come at
15 Hz; the low-level controller ramps each joint's velocity at its acceleration limit (pan
slower than the others). While the target is lost in a camera whose axes are included the
state is invalid: its pixel entries are NaN (the learner acts on its best estimate and learns
nothing), and a transition across a target switch is not learnable.

Vision comes from the camera model with a tracker's faults (`sims.hydra.vision`, the default)
or from rendered images tracked by template matching (`sims.hydra.render`,
`VisionConfig(source="render")`: only the cameras with included axes are looked at);
`camera_images` renders what the cameras see for a person, either way.

Target regimes: `static` (one static target, moved by steps: covered, moved, revealed),
`swing` (the weight swinging on its string), `mixed` (the training apparatus: the swinging
weight and static targets that its cylinder hides one by one), `elastic` (the weight on
elastic, moving in 3D).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.base import TaskEnv, Transition, actions
from sims.hydra.model import (
    GROUP_DISCS,
    GROUP_HEAD,
    GROUP_PENDULUM,
    GROUP_SCENE,
    JOINTS,
    N_DISCS,
    HydraModelConfig,
    disc_y,
    hydra_mjcf,
)
from sims.hydra.vision import Camera, Measurement, VisionConfig
from wfnn_common.config import check_fields

if TYPE_CHECKING:  # cv2 and the GL context load only when something is rendered
    from sims.hydra.render import ImageTracker
    from sims.render import CameraRenderer, RgbImage

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
AXES = ("left_x", "left_y", "right_x", "right_y")
Regime = Literal["static", "swing", "mixed", "elastic"]
REGIMES: tuple[Regime, ...] = ("static", "swing", "mixed", "elastic")


@dataclass(frozen=True, kw_only=True)
class HydraConfig:
    """Which joints and image axes are learned, the target regime, and the task's constants."""

    joints: tuple[str, ...] = ("right",)
    """Included joints, any of pan, tilt, left, right."""
    axes: tuple[str, ...] = ("right_x",)
    """Included image axes, any of left_x, left_y, right_x, right_y."""
    regime: Regime = "swing"
    rate_hz: float = 15.0
    substeps: int = 33
    """Physics steps per action (the physics step is 1 / (rate_hz * substeps))."""
    max_velocity: tuple[float, float, float, float] = (1.0, 1.2, 1.2, 1.2)
    """Largest velocity command per joint (pan, tilt, left, right), rad/s."""
    max_acceleration: tuple[float, float, float, float] = (5.0, 20.0, 20.0, 20.0)
    """Acceleration limit of each joint's low-level controller, rad/s^2 (pan is slower)."""
    limits_deg: tuple[float, float, float, float] = (60.0, 35.0, 40.0, 40.0)
    """Joint range +- (degrees)."""
    initial_verge_deg: float = 5.0
    """Cameras slightly verged at the start (as HyDrA's start-up sequence leaves them)."""
    pixel_velocity_range: float = 600.0
    """Declared range of pixel velocities (px/s) for the learner's scaling."""
    position_weight: float = 1.0
    """Penalty per image axis: position_weight * |x| / (half the image)."""
    velocity_weight: float = 0.25
    """Penalty per image axis: velocity_weight * |dx| / pixel_velocity_range."""
    smoothness_weight: float = 0.25
    """Penalty per joint: smoothness_weight * |previous - new command| / max_velocity."""
    swing_amplitude_deg: tuple[float, float] = (3.0, 8.0)
    """Swing amplitude drawn per episode (degrees of string angle)."""
    static_hold_s: tuple[float, float] = (1.5, 4.0)
    """A static target stays put this long (drawn uniformly) before it is moved."""
    static_hidden_s: float = 0.2
    """How long a static target is covered while it is moved."""
    lost_reset_s: float = 1.5
    """After the target has been lost this long, the head is re-centred and the target set
    going again (what the experimenter does by hand); that transition is not learned."""
    vision: VisionConfig = field(default_factory=VisionConfig)

    def __post_init__(self) -> None:
        check_fields(self)
        for name, chosen, allowed in (("joints", self.joints, JOINTS), ("axes", self.axes, AXES)):
            unknown = set(chosen) - set(allowed)
            if unknown or len(set(chosen)) != len(chosen):
                raise ValueError(f"{name} must be distinct values of {allowed}, got {chosen}")
        if self.regime not in REGIMES:
            raise ValueError(f"regime must be one of {REGIMES}, got {self.regime!r}")
        if not 0 < self.rate_hz <= 1000 or self.substeps < 2:
            raise ValueError(
                f"rate_hz must be in (0, 1000] and substeps >= 2, got {self.rate_hz}, {self.substeps}"
            )

    @property
    def joint_index(self) -> list[int]:
        """Model indices of the included joints, in model order."""
        return [JOINTS.index(j) for j in JOINTS if j in self.joints]

    @property
    def axis_index(self) -> list[int]:
        """Indices of the included image axes, in AXES order."""
        return [AXES.index(a) for a in AXES if a in self.axes]

    @property
    def state_names(self) -> tuple[str, ...]:
        """Names of the state variables, in order."""
        names = [f"{JOINTS[j]}_{q}" for j in self.joint_index for q in ("angle", "velocity")]
        names += [f"{AXES[a]}_{q}" for a in self.axis_index for q in ("error_px", "velocity_px_s")]
        return tuple(names)

    @property
    def reward_names(self) -> tuple[str, ...]:
        """The reward's components (each a penalty)."""
        names = [f"{JOINTS[j]}_smoothness" for j in self.joint_index]
        names += [f"{AXES[a]}_{q}" for a in self.axis_index for q in ("position", "velocity")]
        return tuple(names)


class HydraVec:
    """n simulated HyDrA heads, each with its own apparatus, advanced together."""

    def __init__(self, n: int, config: HydraConfig | None = None, seed: int = 0) -> None:
        cfg = config or HydraConfig()
        self.n = n
        self.config = cfg
        limits = dict(zip(JOINTS, cfg.limits_deg, strict=True))
        model_cfg = HydraModelConfig(
            timestep=1.0 / (cfg.rate_hz * cfg.substeps), elastic=cfg.regime == "elastic",
            apparatus=cfg.regime == "mixed", image_size=(cfg.vision.width, cfg.vision.height),
        )  # fmt: skip
        self.model = mujoco.MjModel.from_xml_string(hydra_mjcf(model_cfg, limits))
        self.model_config = model_cfg
        self.data = [mujoco.MjData(self.model) for _ in range(n)]
        self._rng = np.random.default_rng(seed)
        self.cameras = [
            {c: Camera(self.model, c, cfg.vision, self._rng) for c in ("left", "right")} for _ in range(n)
        ]
        m = self.model
        self._qpos = [int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]) for j in JOINTS]
        self._swing = int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "swing_x")])
        self._swing_dof = int(m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "swing_x")])
        weight = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "weight")
        discs = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"disc{i}") for i in range(N_DISCS)]
        self._disc_mocap = [
            int(m.body_mocapid[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"disc{i}")])
            for i in range(N_DISCS)
        ]
        # Which objects are targets, and what may hide them, in each regime.
        pendulum = cfg.regime in ("swing", "mixed", "elastic")
        self._candidates = ([weight] if pendulum else []) + (
            discs if cfg.regime in ("static", "mixed") else []
        )
        self._groups = np.zeros(6, dtype=np.uint8)
        self._groups[[GROUP_HEAD, GROUP_SCENE, GROUP_DISCS]] = 1
        self._groups[GROUP_PENDULUM] = 1 if pendulum else 0
        # Rendered vision: the cameras whose image axes are included are rendered and tracked
        # by template matching; the others are not looked at.
        self._renderer: CameraRenderer | None = None
        self._image_trackers: list[dict[str, ImageTracker]] = []
        self._rendered_cameras = sorted({AXES[a].split("_")[0] for a in cfg.axis_index})
        if cfg.vision.source == "render":
            from sims.hydra.render import ImageTracker

            self._image_trackers = [
                {c: ImageTracker(cfg.vision) for c in self._rendered_cameras} for _ in range(n)
            ]
        self.command = np.zeros((n, 4))
        """Last velocity command per joint (rad/s); the state's joint velocity."""
        self.setpoint = np.zeros((n, 4))
        """The low-level controller's velocity setpoint per joint: where its ramp toward the
        command has got to (it may take several ticks at the acceleration limit)."""
        self.pixels = np.zeros((n, 4))
        """Latest frame's target pixels per axis (left x, y, right x, y)."""
        self.pixel_velocity = np.zeros((n, 4))
        self.found = np.zeros((n, 2), dtype=np.bool_)
        """Whether each camera (left, right) tracks a target in the latest frame."""
        self.tracked = np.full((n, 2), -1)
        self._last_frame = np.zeros((n, 4))
        self._next_move = np.zeros(n)
        self._hidden_until = np.zeros(n)
        self._lost_since = np.zeros(n)
        self.time = np.zeros(n)
        self.recentred = np.zeros(n, dtype=np.int64)
        """How often each head was re-centred after losing its target too long."""

    # ------------------------------------------------------------------ declared ranges
    @property
    def state_low(self) -> tuple[float, ...]:
        """Declared lower ends of the state variables."""
        return tuple(-v for v in self.state_high)

    @property
    def state_high(self) -> tuple[float, ...]:
        """Declared upper ends (joint limit, max velocity, half image, pixel velocity range)."""
        cfg = self.config
        out: list[float] = []
        for j in cfg.joint_index:
            out += [float(np.deg2rad(cfg.limits_deg[j])), cfg.max_velocity[j]]
        for a in cfg.axis_index:
            half = cfg.vision.width / 2 if AXES[a].endswith("_x") else cfg.vision.height / 2
            out += [half, cfg.pixel_velocity_range]
        return tuple(out)

    @property
    def action_low(self) -> tuple[float, ...]:
        """Desired joint velocities, lower ends."""
        return tuple(-v for v in self.action_high)

    @property
    def action_high(self) -> tuple[float, ...]:
        """Desired joint velocities, upper ends (rad/s)."""
        return tuple(self.config.max_velocity[j] for j in self.config.joint_index)

    # ------------------------------------------------------------------ episodes
    def reset(self, rng: np.random.Generator) -> FloatArray:
        """Heads facing forward with the cameras slightly verged; targets set going."""
        self._rng = rng
        for i, data in enumerate(self.data):
            mujoco.mj_resetData(self.model, data)
            self._centre(i)
            for cam in self.cameras[i].values():
                cam.rng = rng
        self.time[:] = 0.0
        self.new_targets(rng)
        return self.observe()

    def _centre(self, i: int) -> None:
        """The start-up pose: facing forward, cameras slightly verged, at rest."""
        data = self.data[i]
        verge = np.deg2rad(self.config.initial_verge_deg)
        for k, q in enumerate(self._qpos):
            data.qpos[q] = (0.0, 0.0, -verge, verge)[k]
        data.qvel[:] = 0.0
        data.ctrl[:] = 0.0
        self.command[i] = 0.0
        self.setpoint[i] = 0.0
        for cam in self.cameras[i].values():
            cam.reset()
        for tracker in self._image_trackers[i].values() if self._image_trackers else ():
            tracker.reset()
        self._lost_since[i] = self.time[i]

    def new_targets(self, rng: np.random.Generator) -> FloatArray:
        """Set the targets going again (a new swing, a new static position); not learnable across."""
        self._rng = rng
        for i in range(self.n):
            self._restart_target(i)
        return self.observe()

    def _restart_target(self, i: int) -> None:
        """A new swing, or a new static target position (covered for a moment)."""
        cfg, rng, data = self.config, self._rng, self.data[i]
        if cfg.regime in ("swing", "mixed", "elastic"):
            # Released through the bottom of the swing, where the cameras see it at the start.
            amp = np.deg2rad(rng.uniform(*cfg.swing_amplitude_deg)) * rng.choice([-1.0, 1.0])
            omega = np.sqrt(9.81 / self.model_config.string_length)
            data.qpos[self._swing] = 0.0
            data.qvel[self._swing_dof] = amp * omega
            if cfg.regime == "elastic":
                data.qvel[self._swing_dof + 1] = rng.uniform(-0.3, 0.3)
                data.qvel[self._swing_dof + 2] = rng.uniform(-0.3, 0.3)
        self._place_discs(i, rng)
        self._hidden_until[i] = self.time[i] + cfg.static_hidden_s
        self._next_move[i] = self.time[i] + rng.uniform(*cfg.static_hold_s)
        mujoco.mj_forward(self.model, data)
        self._frame(i)
        self._frame(i)

    def _place_discs(self, i: int, rng: np.random.Generator) -> None:
        data, cfg, board = self.data[i], self.config, self.model_config.board_distance - 0.01
        away = np.array([board, 0.0, -10.0])
        for k, mocap in enumerate(self._disc_mocap):
            if cfg.regime == "static":
                pos = np.array([board, rng.uniform(-0.35, 0.25), rng.uniform(-0.1, 0.1)]) if k == 0 else away
            elif cfg.regime == "mixed":
                pos = np.array([board, disc_y(self.model_config, k), self.model_config.disc_height])
            else:
                pos = away
            data.mocap_pos[mocap] = pos

    # ------------------------------------------------------------------ stepping
    def step(self, action: FloatArray) -> Transition:
        """One 15 Hz tick: ramp the joints toward the commanded velocities, track, reward."""
        cfg = self.config
        action = actions(action, self.n, len(cfg.joint_index))
        vmax = np.asarray(cfg.max_velocity)
        before_tracked = self.tracked.copy()
        before_valid = self.valid()
        previous = self.command.copy()
        target = np.zeros((self.n, 4))
        target[:, cfg.joint_index] = np.clip(action, -vmax[cfg.joint_index], vmax[cfg.joint_index])
        dt = self.model.opt.timestep
        steps = np.arange(1, cfg.substeps + 1)[:, None]
        half = cfg.substeps // 2
        moved = np.zeros(self.n, dtype=np.bool_)
        # The low-level controller's velocity ramp at each joint's acceleration limit.
        reach = np.asarray(cfg.max_acceleration) * dt * steps
        for i, data in enumerate(self.data):
            profile = self.setpoint[i] + np.clip(target[i] - self.setpoint[i], -reach, reach)
            for k in range(cfg.substeps):
                data.ctrl[:] = profile[k]
                mujoco.mj_step(self.model, data)
                if k == half - 1 or k == cfg.substeps - 1:
                    self._frame(i)
            self.setpoint[i] = profile[-1]
            self.time[i] += 1.0 / cfg.rate_hz
            moved[i] = self._move_static_target(i)
        self.command = target
        lost = ~self.valid()
        self._lost_since[~lost] = self.time[~lost]
        for stuck in np.flatnonzero(lost & (self.time - self._lost_since > cfg.lost_reset_s)):
            self._centre(int(stuck))
            self._restart_target(int(stuck))
            self.recentred[stuck] += 1
            moved[stuck] = True
        state = self.observe()
        valid = self.valid()
        learnable = before_valid & valid & ~moved & (self.tracked == before_tracked).all(axis=1)
        reward = -self.reward_components(previous, target, state).sum(axis=1)
        return Transition(state, reward, np.zeros(self.n, dtype=np.bool_), learnable)

    def _frame(self, i: int) -> None:
        """One 30 Hz camera frame: both trackers; position and velocity of each image axis."""
        data = self.data[i]
        mujoco.mj_kinematics(self.model, data)
        mujoco.mj_camlight(self.model, data)
        candidates = [(g, data.geom_xpos[g].copy()) for g in self._candidates]
        hidden = self._discs_hidden(i)
        for c, name in enumerate(("left", "right")):
            m: Measurement
            if not self._image_trackers:
                seen = [] if hidden else candidates
                m = self.cameras[i][name].observe(self.model, data, seen, self._groups)
            elif name in self._image_trackers[i]:
                m = self._track_image(i, name, [] if hidden else candidates)
            else:
                m = Measurement(False, np.zeros(2), -1, False)
            self.found[i, c] = m.found
            self.tracked[i, c] = m.target
            cols = [2 * c, 2 * c + 1]
            if m.found:
                fresh = m.switched or np.isnan(self._last_frame[i, cols]).any()
                previous = m.pixel if fresh else self._last_frame[i, cols]
                self.pixel_velocity[i, cols] = (m.pixel - previous) * (2 * self.config.rate_hz)
                self.pixels[i, cols] = m.pixel
                self._last_frame[i, cols] = m.pixel
            else:
                self.pixels[i, cols] = np.nan
                self.pixel_velocity[i, cols] = np.nan
                self._last_frame[i, cols] = np.nan

    def _discs_hidden(self, i: int) -> bool:
        """Whether head i's static target is covered while it is moved."""
        return bool(self.time[i] < self._hidden_until[i] and self.config.regime == "static")

    def _hidden_groups(self, i: int) -> list[int]:
        """Geom groups left out of head i's renders: what the regime covers up."""
        hidden = [] if self._groups[GROUP_PENDULUM] else [GROUP_PENDULUM]
        return hidden + ([GROUP_DISCS] if self._discs_hidden(i) else [])

    def _render(self, i: int, camera: str) -> RgbImage:
        if self._renderer is None:
            from sims.render import CameraRenderer

            v = self.config.vision
            self._renderer = CameraRenderer(self.model, round(v.width * v.render_scale),
                                            round(v.height * v.render_scale))  # fmt: skip
        return self._renderer.rgb(self.data[i], camera, self._hidden_groups(i))

    def _track_image(self, i: int, camera: str, candidates: list[tuple[int, FloatArray]]) -> Measurement:
        """Render one camera's frame and track the target in it by template matching."""
        from sims.render import to_grey

        cfg = self.config.vision
        grey = to_grey(self._render(i, camera))
        tracker = self._image_trackers[i][camera]
        if tracker.template is None:
            self._acquire_template(i, camera, grey, candidates)
        if cfg.image_noise > 0:
            noise = self._rng.standard_normal(grey.shape, dtype=np.float32)
            grey += noise * np.float32(cfg.image_noise)
        return tracker.observe(grey)

    def _acquire_template(
        self, i: int, camera: str, grey: NDArray[np.float32], candidates: list[tuple[int, FloatArray]]
    ) -> None:
        """Cut the target template from a noise-free frame where the first target is in plain view.

        As the experimenter did before a run (Section 7.5.1), once per camera; every head's
        tracker of that camera shares it.
        """
        cam = self.cameras[i][camera]
        data = self.data[i]
        for geom, point in candidates[:1]:
            pixel, depth = cam.project(data, point)
            if depth <= 0 or not cam._visible(self.model, data, geom, point, self._groups):
                return
            radius = float(self.model.geom_size[geom][0]) * cam.focal / depth
            tracker = self._image_trackers[i][camera]
            if tracker.acquire(grey, pixel, radius):
                for trackers in self._image_trackers:
                    trackers[camera].share_template(tracker)

    def camera_images(self, i: int = 0, overlay: bool = True) -> dict[str, RgbImage]:
        """What head i's cameras see now, rendered ({left, right}: [h, w, 3] uint8).

        With `overlay`, the tracker's output is drawn on each tracked camera: the target boxed in
        green (and, for rendered vision, the search window in yellow), a red frame while the
        target is lost.
        """
        from sims.hydra.render import draw_tracker

        out: dict[str, RgbImage] = {}
        for c, name in enumerate(("left", "right")):
            image = self._render(i, name)
            if overlay and (not self._image_trackers or name in self._image_trackers[i]):
                tracker = self._image_trackers[i].get(name) if self._image_trackers else None
                pixel = self.pixels[i, 2 * c : 2 * c + 2] if self.found[i, c] else None
                image = draw_tracker(image, tracker, pixel, self.config.vision.render_scale)
            out[name] = image
        return out

    def close(self) -> None:
        """Release the renderer's GL context, if one was made."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def _move_static_target(self, i: int) -> bool:
        """Static regime: cover the target, move it, reveal it (a step). True when it moved."""
        cfg = self.config
        if cfg.regime != "static" or self.time[i] < self._next_move[i]:
            return False
        self._place_discs(i, self._rng)
        self._hidden_until[i] = self.time[i] + cfg.static_hidden_s
        self._next_move[i] = self.time[i] + self._rng.uniform(*cfg.static_hold_s)
        return True

    # ------------------------------------------------------------------ state and reward
    def valid(self) -> BoolArray:
        """Whether every camera with an included axis tracks its target [n]."""
        cams = sorted({AXES[a].split("_")[0] for a in self.config.axis_index})
        cols = [0 if c == "left" else 1 for c in cams]
        return np.asarray(self.found[:, cols].all(axis=1)) if cols else np.ones(self.n, dtype=np.bool_)

    def joint_angles(self) -> FloatArray:
        """All four joint angles [n, 4] (pan, tilt, left, right), radians."""
        return np.array([[d.qpos[q] for q in self._qpos] for d in self.data])

    def observe(self) -> FloatArray:
        """States [n, S] (pixel entries NaN while the target is lost)."""
        cfg = self.config
        angles = self.joint_angles()
        parts: list[FloatArray] = []
        for j in cfg.joint_index:
            parts += [angles[:, j], self.command[:, j]]
        for a in cfg.axis_index:
            parts += [self.pixels[:, a], self.pixel_velocity[:, a]]
        return np.stack(parts, axis=1) if parts else np.zeros((self.n, 0))

    def reward_components(self, previous: FloatArray, command: FloatArray, state: FloatArray) -> FloatArray:
        """The penalties of Fig 7.6 (positive numbers), [n, len(reward_names)]."""
        cfg = self.config
        vmax = np.asarray(cfg.max_velocity)
        parts = [
            cfg.smoothness_weight * np.abs(command[:, j] - previous[:, j]) / vmax[j] for j in cfg.joint_index
        ]
        offset = 2 * len(cfg.joint_index)
        for k, a in enumerate(cfg.axis_index):
            half = cfg.vision.width / 2 if AXES[a].endswith("_x") else cfg.vision.height / 2
            x, dx = state[:, offset + 2 * k], np.nan_to_num(state[:, offset + 2 * k + 1])
            # A lost target costs half the image, as `pixel_error` charges it: read as 0, losing
            # it was paid the best reward a Gymnasium learner could get (never learned here: a
            # transition to a lost target is not learnable).
            parts += [
                cfg.position_weight * np.where(np.isnan(x), 1.0, np.abs(x) / half),
                cfg.velocity_weight * np.abs(dx) / cfg.pixel_velocity_range,
            ]
        return np.stack(parts, axis=1) if parts else np.zeros((self.n, 0))

    def pixel_error(self) -> FloatArray:
        """Mean |pixel error| over the included axes, half the image where lost [n] (lower is better)."""
        cfg = self.config
        if not cfg.axis_index:
            return np.zeros(self.n)
        errors = []
        for a in cfg.axis_index:
            half = cfg.vision.width / 2 if AXES[a].endswith("_x") else cfg.vision.height / 2
            errors.append(np.where(np.isnan(self.pixels[:, a]), half, np.abs(self.pixels[:, a])))
        return np.mean(errors, axis=0)

    def target_angle(self) -> FloatArray:
        """The weight's string angle (rad) [n] (0 at rest; the swing the head follows)."""
        return np.array([d.qpos[self._swing] for d in self.data])


class HydraEnv(TaskEnv):
    """Gymnasium HyDrA: episodes of `max_steps` ticks; lost-target pixels read as 0, cost half the image.

    `render_mode="rgb_array"`: `render()` returns the left and right camera views side by side,
    with the tracker's output drawn.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 15}  # noqa: RUF012

    def __init__(
        self, config: HydraConfig | None = None, max_steps: int = 450, render_mode: str | None = None
    ) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.hydra = HydraVec(1, config)
        super().__init__(self.hydra, max_steps)
        self.render_mode = render_mode

    def _obs(self, state: FloatArray) -> FloatArray:
        return super()._obs(np.nan_to_num(state))

    def render(self) -> RgbImage | None:
        """Both cameras' views side by side [h, 2w, 3] (None without a render mode)."""
        if self.render_mode is None:
            return None
        views = self.hydra.camera_images(0)
        return np.concatenate([views["left"], views["right"]], axis=1)

    def close(self) -> None:
        """Release the renderer."""
        self.hydra.close()
        super().close()
