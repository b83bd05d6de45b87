"""What the Nomad senses (thesis Sections 6.3-6.5, 6.7.1): encoders, infrared ring, camera.

At the end of each action (`sense`) the encoders report the base's velocity with noise and,
rarely, a wild value; the infrared ring measures the distance to what is around the base; the
camera's carpet match matrix is measured and filtered (Eq 6.2); a collision is counted when the
base starts touching something. Every 30 Hz camera frame (`frame`) the tracker follows its
target: the target's pixel error to the goal and its pixel velocity. The interest operator
(`interesting`, `acquire`) picks an object to track out of the carpet matrix.

Vision comes from the camera model (`sims.nomad.vision`) or from rendered images
(`sims.nomad.render`, `NomadVisionConfig(source="render")`); `camera_images` renders what the
camera sees for a person, either way.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.nomad.config import NomadConfig
from sims.nomad.model import GROUP_FLOOR, GROUP_OBJECTS, GROUP_STATIC, NomadModelConfig, NomadParts
from sims.nomad.vision import (
    COLS,
    ROWS,
    NomadCamera,
    TargetTracker,
    Track,
    carpet_mismatch,
    interesting_cells,
    smooth_carpet,
)

if TYPE_CHECKING:  # cv2 and the GL context load only when something is rendered
    from sims.hydra.render import ImageTracker
    from sims.nomad.render import CarpetGrid, FloatImage
    from sims.render import CameraRenderer, RgbImage

FloatArray = NDArray[np.float64]
WILD_ENCODER = -299_792_458.0
"""What the thesis' encoders once reported: the speed of light, backwards (Section 6.7.1)."""
IR_BEAM_DEG = 7.5
"""Half-width of an infrared sensor's beam (degrees; 16 sensors are 22.5 degrees apart)."""
Cut = tuple[FloatArray, float]
"""Rendered vision: where a target's template is cut (pixel, radius; image units)."""
Seen = tuple[int, FloatArray, Cut | None]
"""An interesting object: its geom, the world point seen, and (rendered vision) its pixel and
radius in the image, where its template is cut."""


class Sensing:
    """n Nomads' senses, and what they last reported."""

    def __init__(
        self,
        model: mujoco.MjModel,
        data: list[mujoco.MjData],
        parts: NomadParts,
        config: NomadConfig,
        model_config: NomadModelConfig,
        rng: np.random.Generator,
    ) -> None:
        n = len(data)
        self.model, self.data, self.parts = model, data, parts
        self.config, self.model_config = config, model_config
        self.rng = rng
        """The generator the senses' noise comes from (the task's, changed with it)."""
        self.camera = NomadCamera(model, config.vision, parts.base_body)
        self.trackers = [TargetTracker(self.camera, rng) for _ in range(n)]
        angles = 2 * np.pi * np.arange(config.ir_sensors) / config.ir_sensors
        self.ir_angles = angles
        """Directions of the infrared sensors in the robot's frame (rad, 0 ahead, counter-clockwise)."""
        # Each sensor's beam is a cone: rays at its centre and +-IR_BEAM_DEG, the nearest reading
        # counts (a single ray per sensor slips past a shoe between two sensors).
        beam = (angles[:, None] + np.deg2rad([0.0, -IR_BEAM_DEG, IR_BEAM_DEG])).ravel()
        self._ir_dirs = np.stack([np.cos(beam), np.sin(beam), np.zeros_like(beam)], axis=1)
        self._ir_groups = np.ones(6, dtype=np.uint8)
        self._ir_groups[GROUP_FLOOR] = 0
        # A collision is the base touching anything but the floor and the balls (which it may
        # nudge while pursuing them).
        self._harmless = {parts.floor, *parts.ball_geoms}
        self.measured = np.zeros((n, 2))
        """The encoders' (t, r) this tick (possibly wild)."""
        self.ir = np.full((n, config.ir_sensors), config.ir_range)
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
        self.collisions = np.zeros(n, dtype=np.int64)
        self._touching = np.zeros(n, dtype=np.bool_)
        self._renderer: CameraRenderer | None = None
        """Renders full-size pictures for a person (`camera_images`)."""
        # Rendered vision: each robot's latest frame, when (sim time) it was rendered, and where a
        # newly started target's template is to be cut (pixel, radius; image units).
        self.rendered = config.vision.source == "render"
        self._vision_renderer: CameraRenderer | None = None
        self._frames: list[FloatImage | None] = [None] * n
        self._frame_time = np.full(n, -1.0)
        self._cut: list[Cut | None] = [None] * n
        self._grid: CarpetGrid | None = None
        self._image_trackers: list[ImageTracker] = []
        if self.rendered:
            from sims.hydra.render import ImageTracker
            from sims.nomad.render import CarpetGrid

            self._grid = CarpetGrid(config.vision)
            self._image_trackers = [ImageTracker(config.vision) for _ in range(n)]

    def reset(self, i: int, rng: np.random.Generator) -> None:
        """A new episode for robot i: nothing tracked, nothing measured yet (its tracker draws from `rng`)."""
        self.trackers[i].rng = rng
        self.trackers[i].stop()
        self._frame_time[i] = -1.0
        self.measured[i] = 0.0
        self.carpet[i] = 0.0
        self._touching[i] = False

    def scene_changed(self, i: int) -> None:
        """Something in robot i's room was moved by hand: a rendered frame of it is out of date."""
        self._frame_time[i] = -1.0

    # ------------------------------------------------------------------ at the end of an action
    def sense(self, i: int, first: bool = False) -> None:
        """Encoders, infrared ring, carpet matrix and collisions at the end of an action.

        `first`: at the start of an episode (at rest; no previous carpet matrix to filter with).
        """
        cfg, data, rng = self.config, self.data[i], self.rng
        true = self.parts.velocity(data) if not first else np.zeros(2)
        self.measured[i] = true + rng.normal(0.0, cfg.encoder_noise)
        if rng.random() < cfg.encoder_glitch:
            self.measured[i, 0] = WILD_ENCODER
        heading = data.qpos[self.parts.q[2]]
        rot = np.array(
            [[np.cos(heading), -np.sin(heading), 0], [np.sin(heading), np.cos(heading), 0], [0, 0, 1]]
        )
        origin = np.array(
            [data.qpos[self.parts.q[0]], data.qpos[self.parts.q[1]], self.model_config.ir_height]
        )
        dirs = self._ir_dirs @ rot.T
        rays = len(dirs)
        geoms = np.zeros(rays, dtype=np.int32)
        dist = np.zeros(rays)
        cutoff = self.model_config.radius + cfg.ir_range
        mujoco.mj_multiRay(self.model, data, origin, dirs.ravel(), self._ir_groups, 1, self.parts.base_body,
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
        touching = any(
            self.parts.base_geom in (c.geom1, c.geom2) and not {c.geom1, c.geom2} & self._harmless
            for c in data.contact[: data.ncon]
        )
        if touching and not self._touching[i]:
            self.collisions[i] += 1
        self._touching[i] = touching

    # ------------------------------------------------------------------ the camera's frames
    def frame(self, i: int) -> None:
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
            self._grid.acquire(to_colour(self._carpet_view(), v.image_noise, self.rng))
        frame = to_colour(self._vision_renderer.rgb(data, "camera"), v.image_noise, self.rng)
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

    # ------------------------------------------------------------------ targets
    def follow(self, i: int, geom: int, point: FloatArray, cut: Cut | None = None) -> None:
        """Track `geom` from its world `point` on, starting with a frame now.

        Rendered vision: its template is cut at `cut` (pixel, radius) in that frame.
        """
        self.trackers[i].start(self.data[i], geom, point)
        self._cut[i] = cut
        self._last_frame[i] = np.nan
        self.frame(i)

    def follow_ball(self, i: int, geom: int) -> None:
        """Track a ball the experimenter placed in view, from its centre (where its template is cut)."""
        data = self.data[i]
        point = data.geom_xpos[geom].copy()
        cut = None
        if self.rendered:
            pixel, depth = self.camera.project(data, point)
            cut = (pixel, self.model_config.ball_radius * self.camera.focal / max(depth, 1e-6))
        self.follow(i, geom, point, cut)

    def forget(self, i: int) -> None:
        """Robot i's tracker lets its target go (it was taken away)."""
        self.trackers[i].stop()
        self.pixels[i] = self.pixel_velocity[i] = self._last_frame[i] = np.nan

    def interesting(self, i: int) -> list[tuple[int, FloatArray]]:
        """The interest operator on robot i's latest raw carpet matrix.

        Returns, per interesting object, the geom its rays met most and the mean point where
        they met it (where a template of it would be taken): [(geom, point [3])]. Rendered
        vision: the geom and point the ray through the object's pixel meets.
        """
        return [(geom, point) for geom, point, _ in self._objects(i)]

    def acquire(self, i: int) -> bool:
        """Run the interest operator for robot i and track the first interesting object found.

        Returns whether one was found (the tracker may lose it in its first frame).
        """
        found = self._objects(i)
        if not found:
            return False
        geom, point, seen = found[0]
        self.follow(i, geom, point, seen)
        return True

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
            chosen = geoms[(geoms >= 0) & (geoms != self.parts.floor)]
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
            if geom >= 0 and geom != self.parts.floor:
                out.append((geom, point, seen))
        return out

    def tracked(self) -> NDArray[np.int64]:
        """The geom each robot's tracker follows [n] (-1: none)."""
        return np.array([t.geom for t in self.trackers])

    def pixel_error(self) -> FloatArray:
        """servo: |pixel error to the goal| [n], half the image diagonal where no target is tracked."""
        half_diagonal = self.config.vision.half_diagonal
        return np.where(np.isnan(self.pixels[:, 0]), half_diagonal, np.hypot(*np.nan_to_num(self.pixels).T))

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
