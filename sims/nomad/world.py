"""The Nomad's room and what happens in it (thesis Sections 6.4-6.6): the experimenter's part.

Each episode starts with the robot at a free place and the balls scattered about the room.
For servoing the experimenter places a ball in view ahead of the camera (a step for the
servoing), and places it again after the target has been lost for a while; a ball the foraging
robot reached is picked up and put somewhere else. A person walks to and fro along the south
wall, waiting for a robot in their way.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np
from numpy.typing import NDArray

from sims.nomad.config import NomadConfig
from sims.nomad.model import NomadModelConfig, NomadParts

if TYPE_CHECKING:
    from sims.nomad.sensing import Sensing

FloatArray = NDArray[np.float64]
PERSON_PATIENCE_S = 3.0
"""How long the walking person waits for a robot in their way before turning back."""


class World:
    """n rooms, each with its robot, balls and person; targets placed as the experimenter did."""

    def __init__(
        self,
        model: mujoco.MjModel,
        data: list[mujoco.MjData],
        parts: NomadParts,
        config: NomadConfig,
        model_config: NomadModelConfig,
        sensing: Sensing,
        time: FloatArray,
    ) -> None:
        n = len(data)
        self.model, self.data, self.parts = model, data, parts
        self.config, self.model_config = config, model_config
        self.sensing = sensing
        """The robots' senses: a placed target is tracked, a moved ball makes a rendered frame stale."""
        self.time = time
        """Each robot's sim time [n] (the task's, advanced in place)."""
        self.placed = np.zeros(n, dtype=np.int64)
        """Targets placed (servo)."""
        self._lost_since = np.zeros(n)
        """servo: when each robot's tracker last had its target."""
        self._person_walked = np.zeros(n)
        """Metres the person has walked (they wait while a robot is in their way)."""
        self._person_waited = np.zeros(n)

    def reset(self, i: int, rng: np.random.Generator) -> None:
        """Robot i at a free place facing anywhere, its balls scattered; the person back at the start."""
        x, y = self._free_spot(rng, 0.8)
        self.data[i].qpos[self.parts.q] = (x, y, rng.uniform(-np.pi, np.pi))
        self.scatter_balls(i, rng)
        self._person_walked[i] = 0.0
        self._person_waited[i] = 0.0

    # ------------------------------------------------------------------ places
    def _free_spot(self, rng: np.random.Generator, clearance: float) -> tuple[float, float]:
        ax, ay = (s / 2 - clearance for s in self.model_config.arena)
        for _ in range(1000):
            x, y = rng.uniform(-ax, ax), rng.uniform(-ay, ay)
            if self._clear(x, y, clearance):
                return float(x), float(y)
        raise RuntimeError("no free spot in the arena")

    def _clear(self, x: float, y: float, clearance: float) -> bool:
        """Whether (x, y) is further than `clearance` outside every obstacle's keep-out radius."""
        return all(np.hypot(x - ox, y - oy) > r + clearance for ox, oy, r in self.parts.obstacles)

    def _spot_away(self, i: int, rng: np.random.Generator, distance: float) -> tuple[float, float]:
        """A free place for a ball, at least `distance` from robot i's centre (100 tries)."""
        robot = self.data[i].qpos[self.parts.q[:2]]
        for _ in range(100):
            xy = self._free_spot(rng, 0.4)
            if np.hypot(xy[0] - robot[0], xy[1] - robot[1]) > distance:
                break
        return xy

    # ------------------------------------------------------------------ balls and targets
    def scatter_balls(self, i: int, rng: np.random.Generator) -> None:
        """Put robot i's balls at random free places (not under the robot)."""
        for k in range(len(self.parts.balls)):
            self.put_ball(i, k, self._spot_away(i, rng, self.model_config.radius + 0.3))

    def put_ball(self, i: int, k: int, xy: tuple[float, float]) -> None:
        """Ball k of robot i's room at rest on the floor at `xy` (call mj_forward after)."""
        q, v = self.parts.balls[k]
        data = self.data[i]
        data.qpos[q : q + 7] = (xy[0], xy[1], self.model_config.ball_radius, 1, 0, 0, 0)
        data.qvel[v : v + 6] = 0.0
        self.sensing.scene_changed(i)

    def place_target(self, i: int, rng: np.random.Generator) -> None:
        """Put a ball in view ahead of the camera and start tracking it.

        As the interest operator would pick an isolated ball; the other balls go out of the way.
        """
        cfg, data = self.config, self.data[i]
        x, y, heading = (data.qpos[q] for q in self.parts.q)
        look = heading + np.deg2rad(cfg.camera_yaw_deg)
        k = int(rng.integers(len(self.parts.balls)))
        ax, ay = (s / 2 - 0.3 for s in self.model_config.arena)
        for _ in range(100):
            dist = rng.uniform(*cfg.target_distance) + self.model_config.camera_forward
            bearing = look + np.deg2rad(rng.uniform(-cfg.target_bearing_deg, cfg.target_bearing_deg))
            bx, by = x + dist * np.cos(bearing), y + dist * np.sin(bearing)
            if abs(bx) < ax and abs(by) < ay and self._clear(bx, by, 0.0):
                break
        else:  # nowhere in view: turn the robot round and try again next time
            data.qpos[self.parts.q[2]] += np.pi
        for other in range(len(self.parts.balls)):
            if other != k:
                self.put_ball(i, other, self._free_spot(rng, 0.4))
        self.put_ball(i, k, (bx, by))
        mujoco.mj_forward(self.model, data)
        self.placed[i] += 1
        self.sensing.follow_ball(i, self.parts.ball_geoms[k])
        self.target_seen(i)

    def target_seen(self, i: int) -> None:
        """Robot i's tracker has its target now (the time it has been lost starts again)."""
        self._lost_since[i] = self.time[i]

    def replace_lost_target(self, i: int, rng: np.random.Generator) -> bool:
        """servo: a target lost for `lost_reset_s` is placed again in view. True if so."""
        cfg = self.config
        if cfg.behaviour != "servo":
            return False
        if self.sensing.trackers[i].active:
            self.target_seen(i)
            return False
        if self.time[i] - self._lost_since[i] < cfg.lost_reset_s:
            return False
        self.place_target(i, rng)
        return True

    def collect(self, i: int, rng: np.random.Generator) -> None:
        """Robot i has reached its target: a ball is picked up and put somewhere else; tracking stops."""
        geom = self.sensing.trackers[i].geom
        if geom in self.parts.ball_geoms:
            k = self.parts.ball_geoms.index(geom)
            self.put_ball(i, k, self._spot_away(i, rng, 2.0))  # not straight back into view
            mujoco.mj_forward(self.model, self.data[i])
        self.sensing.forget(i)

    # ------------------------------------------------------------------ the person
    def move_person(self, i: int) -> None:
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
        ahead = (data.qpos[self.parts.q[0]] - x) * heading
        if -0.2 < ahead < 0.3 + self.model_config.radius + 0.5 and abs(data.qpos[self.parts.q[1]] - y) < 0.7:
            self._person_waited[i] += 1.0 / cfg.rate_hz
            if self._person_waited[i] >= PERSON_PATIENCE_S:
                self._person_walked[i] = 2 * span - phase  # the same place, facing the other way
                self._person_waited[i] = 0.0
        else:
            self._person_waited[i] = 0.0
            self._person_walked[i] += cfg.person_speed / cfg.rate_hz
        data.mocap_pos[self.parts.person] = (x, y, 0.0)
        half = 0.0 if heading > 0 else np.pi
        data.mocap_quat[self.parts.person] = (np.cos(half / 2), 0.0, 0.0, np.sin(half / 2))
