"""MJCF of a Nomad 200-like mobile robot in an office-like arena (thesis Section 6.2, Fig 6.1-6.2).

The robot: a round base that translates forward/backward and rotates (a planar root: world x,
y slides and a yaw hinge), velocity-commanded through actuators in its own frame (forward, and
sideways held at zero so it cannot slip sideways, as wheels would not), a ring of infrared
proximity sensors (rays cast by the task), and a colour camera on top looking forward and
downward, optionally turned away from the direction of travel (Fig 6.14).

The arena: carpet, walls of a colour close to the carpet's, pillars, a potted plant whose
foliage stays within its pot (the ground-plane constraint), balls to pursue (free bodies the
robot can push), and a person's feet and legs that walk (mocap bodies).

World frame: x east, y north, z up; the floor is z = 0. The robot's forward is its body x.

`NomadParts` finds the named parts (the base's joints, the balls, the person, the obstacles) in
the compiled model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import NDArray

from wfnn_common.config import check_fields

FloatArray = NDArray[np.float64]

# Geom groups: what the infrared rays and the camera's rays may hit.
GROUP_ROBOT, GROUP_FLOOR, GROUP_STATIC, GROUP_OBJECTS = 0, 1, 2, 3
BALL_COLOURS = (
    (0.85, 0.1, 0.1), (0.95, 0.8, 0.1), (0.1, 0.55, 0.15),
    (0.9, 0.45, 0.05), (0.6, 0.1, 0.6), (0.95, 0.95, 0.9),
)  # fmt: skip
N_BALLS = len(BALL_COLOURS)
"""Balls in the arena by default (one of each colour)."""
CARPET = (0.33, 0.36, 0.45)
"""Colour of the carpet (RGB, 0..1)."""


@dataclass(frozen=True, kw_only=True)
class NomadModelConfig:
    """Geometry of the robot, its camera and the arena."""

    radius: float = 0.23
    """Base radius (m); the Nomad 200 is about 46 cm across."""
    height: float = 0.78
    mass: float = 60.0
    camera_height: float = 1.0
    camera_forward: float = 0.2
    """Camera position ahead of the base centre (m): far enough that it does not see the base."""
    camera_pitch_deg: float = 35.0
    """Camera pointing down from horizontal."""
    camera_yaw_deg: float = 0.0
    """Camera turned from the direction of travel (misaligned camera, Fig 6.14; positive: left)."""
    fovy_deg: float = 40.0
    ir_height: float = 0.06
    """Height of the infrared ring (m): low enough to see a person's shoes."""
    arena: tuple[float, float] = (8.0, 6.0)
    """Room size, x by y (m)."""
    wall_colour: tuple[float, float, float] = (0.48, 0.48, 0.55)
    """Close to the carpet's colour, as in the thesis' corridors (a mismatch of about 0.6)."""
    ball_radius: float = 0.1
    balls: int = N_BALLS
    """Balls in the arena (colours repeat beyond six)."""
    pillars: tuple[tuple[float, float], ...] = ((-1.5, 1.0), (1.8, -1.2), (2.2, 1.6))
    plant: tuple[float, float] = (-2.4, -1.6)
    timestep: float = 0.002
    """Physics step (s): 50 steps per 10 Hz action."""
    image_size: tuple[int, int] = (320, 240)

    def __post_init__(self) -> None:
        check_fields(self)


MAX_BALLS = 100
"""Most balls an arena holds."""


def nomad_mjcf(cfg: NomadModelConfig) -> str:
    """The MJCF text of the robot and the arena."""
    if not 1 <= cfg.balls <= MAX_BALLS:  # each is a body in the model: thousands would not load
        raise ValueError(f"balls must be in [1, {MAX_BALLS}], got {cfg.balls}")
    ax, ay = cfg.arena[0] / 2, cfg.arena[1] / 2
    wall = " ".join(f"{c:.3f}" for c in cfg.wall_colour) + " 1"
    carpet = " ".join(f"{c:.3f}" for c in CARPET) + " 1"
    walls = "\n".join(
        f'<geom name="wall{k}" type="box" size="{sx} {sy} 0.5" pos="{px} {py} 0.5" rgba="{wall}" '
        f'material="matte" group="{GROUP_STATIC}"/>'
        for k, (sx, sy, px, py) in enumerate(
            (
                (ax, 0.05, 0, ay + 0.05),
                (ax, 0.05, 0, -ay - 0.05),
                (0.05, ay, ax + 0.05, 0),
                (0.05, ay, -ax - 0.05, 0),
            )
        )
    )
    pillars = "\n".join(
        f'<geom name="pillar{k}" type="box" size="0.15 0.15 1.2" pos="{x} {y} 1.2" rgba="0.85 0.85 0.82 1" '
        f'group="{GROUP_STATIC}"/>'
        for k, (x, y) in enumerate(cfg.pillars)
    )
    px, py = cfg.plant
    plant = (
        f'<geom name="pot" type="cylinder" size="0.2 0.2" pos="{px} {py} 0.2" rgba="0.45 0.25 0.12 1" '
        f'group="{GROUP_STATIC}"/>'
        f'<geom name="foliage" type="ellipsoid" size="0.19 0.19 0.35" pos="{px} {py} 0.72" '
        f'rgba="0.15 0.45 0.12 1" group="{GROUP_STATIC}"/>'
    )
    balls = "\n".join(
        f'<body name="ball{k}" pos="{-3.0 + k % 7} {ay - 0.5 - 0.3 * (k // 7)} {cfg.ball_radius}">'
        f'<freejoint name="ball{k}"/><geom name="ball{k}" type="sphere" size="{cfg.ball_radius}" mass="0.3" '
        f'rgba="{r} {g} {b} 1" group="{GROUP_OBJECTS}" condim="3" friction="0.8 0.02 0.001"/></body>'
        for k, (r, g, b) in ((k, BALL_COLOURS[k % len(BALL_COLOURS)]) for k in range(cfg.balls))
    )
    # A person: two black shoes and dark trouser legs, moved as one mocap body.
    shoe = f'type="box" size="0.14 0.05 0.04" rgba="0.05 0.05 0.05 1" group="{GROUP_OBJECTS}"'
    leg = f'type="capsule" size="0.06" rgba="0.1 0.1 0.25 1" group="{GROUP_OBJECTS}"'
    person = (
        f'<body name="person" mocap="true" pos="{ax - 0.6} {-ay + 0.6} 0">'
        f'<geom name="shoe_l" {shoe} pos="0.04 0.12 0.04"/><geom name="shoe_r" {shoe} pos="0.04 -0.12 0.04"/>'
        f'<geom name="leg_l" {leg} fromto="0 0.12 0.1 0 0.12 0.9"/>'
        f'<geom name="leg_r" {leg} fromto="0 -0.12 0.1 0 -0.12 0.9"/>'
        "</body>"
    )
    w, h = cfg.image_size
    cam_x = cfg.camera_forward
    # MuJoCo cameras look along their -z with +y up: image right is the robot's right (-y),
    # the view direction is forward and down by the pitch.
    pitch = math.radians(cfg.camera_pitch_deg)
    sp, cp = math.sin(pitch), math.cos(pitch)
    return f"""
<mujoco model="nomad">
  <option timestep="{cfg.timestep}" integrator="implicitfast"/>
  <visual><global offwidth="{max(640, w)}" offheight="{max(480, h)}"/></visual>
  <default><geom contype="1" conaffinity="1" friction="0.6 0.01 0.001"/></default>
  <!-- Carpet and walls are matte: a glint of a light moves with the camera's view and would
       read as "not carpet". -->
  <asset><material name="matte" specular="0" shininess="0" reflectance="0"/></asset>
  <worldbody>
    <!-- Directional lights: the floor is lit the same everywhere (spotlights' cones made the
         carpet three times darker in the room's corners than in its middle). -->
    <light directional="true" pos="0 0 3" dir="0 0 -1" diffuse="0.6 0.6 0.6"/>
    <light directional="true" pos="2 2 3" dir="-0.3 -0.3 -1" diffuse="0.3 0.3 0.3"/>
    <geom name="floor" type="plane" size="{ax} {ay} 0.1" rgba="{carpet}" material="matte"
          group="{GROUP_FLOOR}"/>
    {walls}
    {pillars}
    {plant}
    {balls}
    {person}
    <body name="base" pos="0 0 0">
      <joint name="x" type="slide" axis="1 0 0" damping="0"/>
      <joint name="y" type="slide" axis="0 1 0" damping="0"/>
      <joint name="yaw" type="hinge" axis="0 0 1" damping="0"/>
      <geom name="base" type="cylinder" size="{cfg.radius} {cfg.height / 2}" pos="0 0 {cfg.height / 2 + 0.02}"
            mass="{cfg.mass}" rgba="0.8 0.8 0.78 1" group="{GROUP_ROBOT}"/>
      <geom name="mast" type="box" size="0.04 0.04 {(cfg.camera_height - cfg.height) / 2}" contype="0"
            conaffinity="0" pos="{cam_x} 0 {(cfg.camera_height + cfg.height) / 2}" mass="0.5"
            group="{GROUP_ROBOT}"/>
      <site name="drive" pos="0 0 {cfg.height / 2}"/>
      <body name="camera_mount" pos="{cam_x} 0 {cfg.camera_height}" euler="0 0 {cfg.camera_yaw_deg}">
        <camera name="camera" xyaxes="0 -1 0 {sp:.6f} 0 {cp:.6f}" fovy="{cfg.fovy_deg}"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <velocity name="forward" site="drive" gear="1 0 0 0 0 0" kv="{60 * cfg.mass}"/>
    <velocity name="sideways" site="drive" gear="0 1 0 0 0 0" kv="{60 * cfg.mass}"/>
    <velocity name="turn" joint="yaw" kv="{150 * cfg.mass * cfg.radius**2}"/>
  </actuator>
</mujoco>
"""


@dataclass(frozen=True)
class NomadParts:
    """Where `nomad_mjcf`'s named parts are in the compiled model (`find`)."""

    q: list[int]
    """qpos addresses of the base's (x, y, yaw) joints."""
    v: list[int]
    """qvel addresses of the base's (x, y, yaw) joints."""
    balls: list[tuple[int, int]]
    """qpos and qvel addresses of each ball's free joint."""
    ball_geoms: list[int]
    person: int
    """The walking person's mocap index."""
    base_body: int
    base_geom: int
    floor: int
    obstacles: list[tuple[float, float, float]]
    """(x, y, keep-out radius) of the fixed obstacles (pillars, the plant), for placing things."""

    @classmethod
    def find(cls, model: mujoco.MjModel, balls: int) -> NomadParts:
        """The parts of a model of `balls` balls."""

        def joint(name: str) -> tuple[int, int]:
            j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
            return int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])

        def geom(name: str) -> int:
            return int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name))

        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or "" for g in range(model.ngeom)]
        return cls(
            q=[joint(j)[0] for j in ("x", "y", "yaw")],
            v=[joint(j)[1] for j in ("x", "y", "yaw")],
            balls=[joint(f"ball{k}") for k in range(balls)],
            ball_geoms=[geom(f"ball{k}") for k in range(balls)],
            person=int(model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "person")]),
            base_body=int(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "base")),
            base_geom=geom("base"),
            floor=geom("floor"),
            obstacles=[
                (float(model.geom_pos[g][0]), float(model.geom_pos[g][1]), 0.5)
                for g, name in enumerate(names)
                if name == "pot" or name.startswith("pillar")
            ],
        )

    def pose(self, data: mujoco.MjData) -> FloatArray:
        """The robot's (x, y, heading) [3]."""
        return np.asarray(data.qpos[self.q])

    def velocity(self, data: mujoco.MjData) -> FloatArray:
        """The robot's true (forward, rotational) velocity [2]."""
        heading = data.qpos[self.q[2]]
        vx, vy = data.qvel[self.v[0]], data.qvel[self.v[1]]
        return np.array([vx * np.cos(heading) + vy * np.sin(heading), data.qvel[self.v[2]]])
