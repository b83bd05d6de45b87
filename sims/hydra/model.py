"""MJCF of a HyDrA-like binocular active head and its targets (thesis Section 7.3, Fig 7.5).

The head: a pan joint (about the vertical), a tilt joint common to both cameras (Helmholtz
configuration: tilt before the verge axes), and independent left and right verge-axis joints,
each velocity-commanded with joint limits. The narrow-field cameras sit slightly in front of and
beside their verge axes (parallax, as on the worn real head). The targets: a weight on a 1.6 m
string hanging 0.64 m in front of the cameras (a planar swing, or 3D on elastic), a white
cylinder hanging below it (the training apparatus of Section 7.5.2), and static black discs on
a white board behind, moved as mocap bodies.

World frame: x forward (away from the head), y to the head's left, z up; the cameras are at
z = 0 at rest.
"""

from __future__ import annotations

from dataclasses import dataclass

JOINTS = ("pan", "tilt", "left", "right")
"""Joint names in model order."""
CAMERAS = ("left", "right")
N_DISCS = 4

# Geom groups, so rays (the camera's line of sight) can leave the pendulum out.
GROUP_HEAD, GROUP_PENDULUM, GROUP_SCENE = 0, 1, 2


@dataclass(frozen=True, kw_only=True)
class HydraModelConfig:
    """Geometry and dynamics of the simulated head and apparatus."""

    baseline: float = 0.2
    """Distance between the verge axes (m)."""
    camera_offset: tuple[float, float] = (0.02, 0.004)
    """Camera centre forward of and beside its verge axis (m): parallax, as on the real head."""
    fovy_deg: float = 24.0
    """Vertical field of view of each (narrow-field) camera."""
    string_length: float = 1.6
    target_distance: float = 0.64
    """Distance from the cameras to the weight at rest (m)."""
    board_distance: float = 1.0
    """Distance to the white board with the static targets (m)."""
    elastic: bool = False
    """Hang the weight on elastic (3D motion) instead of string (planar swing)."""
    elastic_stiffness: float = 60.0
    """N/m of the elastic."""
    apparatus: bool = True
    """Hang the white cylinder below the weight (it hides static targets as it swings past)."""
    timestep: float = 1.0 / (15 * 33)
    """Physics step (s): 33 steps per 15 Hz control tick."""


def _joint(name: str, axis: str, limit_deg: float, armature: float) -> str:
    return (
        f'<joint name="{name}" type="hinge" axis="{axis}" range="-{limit_deg} {limit_deg}" '
        f'limited="true" armature="{armature}" damping="0"/>'
    )


def hydra_mjcf(cfg: HydraModelConfig, limits_deg: dict[str, float]) -> str:
    """The MJCF text of the head and the apparatus."""
    half = cfg.baseline / 2
    fwd, side = cfg.camera_offset
    # MuJoCo cameras look along their -z with +y up: x_cam = world -y, y_cam = world +z.
    cam = f'xyaxes="0 -1 0 0 0 1" fovy="{cfg.fovy_deg}"'
    anchor = (cfg.target_distance, 0.0, cfg.string_length)
    if cfg.elastic:
        suspension = (
            '<joint name="swing_x" type="hinge" axis="1 0 0" damping="0.002"/>'
            '<joint name="swing_y" type="hinge" axis="0 1 0" damping="0.002"/>'
            f'<joint name="stretch" type="slide" axis="0 0 -1" stiffness="{cfg.elastic_stiffness}" '
            'damping="0.05" range="-0.3 0.6" limited="true"/>'
        )
    else:
        suspension = '<joint name="swing_x" type="hinge" axis="1 0 0" damping="0.0005"/>'
    cylinder = (
        '<geom name="cylinder" type="cylinder" size="0.025 0.14" pos="0 0 -0.2" rgba="1 1 1 1" '
        f'mass="0.05" group="{GROUP_PENDULUM}"/>'
        if cfg.apparatus
        else ""
    )
    discs = "\n".join(
        f'<body name="disc{i}" mocap="true" pos="{cfg.board_distance - 0.01} {0.3 - 0.2 * i} -0.15">'
        f'<geom name="disc{i}" type="cylinder" size="0.02 0.002" euler="0 90 0" rgba="0 0 0 1" '
        f'contype="0" conaffinity="0" group="{GROUP_SCENE}"/></body>'
        for i in range(N_DISCS)
    )
    head_body = 'gravcomp="1"'
    return f"""
<mujoco model="hydra">
  <option timestep="{cfg.timestep}" integrator="implicitfast"/>
  <visual><global offwidth="640" offheight="480"/></visual>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1"/>
    <geom name="board" type="box" size="0.005 0.8 0.6" pos="{cfg.board_distance + 0.005} 0 0"
          rgba="1 1 1 1" group="{GROUP_SCENE}"/>
    {discs}
    <body name="pan_link" pos="0 0 -0.12" {head_body}>
      {_joint("pan", "0 0 1", limits_deg["pan"], 0.05)}
      <geom type="cylinder" size="0.06 0.04" mass="1.0" rgba="0.3 0.3 0.3 1" group="{GROUP_HEAD}"/>
      <body name="tilt_link" pos="0 0 0.12" {head_body}>
        {_joint("tilt", "0 -1 0", limits_deg["tilt"], 0.02)}
        <geom type="box" size="0.03 {half + 0.03} 0.01" pos="0 0 -0.03" mass="0.5" group="{GROUP_HEAD}"/>
        <body name="left_link" pos="0 {half} 0" {head_body}>
          {_joint("left", "0 0 1", limits_deg["left"], 0.005)}
          <geom type="box" size="0.03 0.02 0.02" pos="{fwd} {side} 0" mass="0.2" group="{GROUP_HEAD}"/>
          <camera name="left" pos="{fwd + 0.03} {side} 0" {cam}/>
        </body>
        <body name="right_link" pos="0 {-half} 0" {head_body}>
          {_joint("right", "0 0 1", limits_deg["right"], 0.005)}
          <geom type="box" size="0.03 0.02 0.02" pos="{fwd} {-side} 0" mass="0.2" group="{GROUP_HEAD}"/>
          <camera name="right" pos="{fwd + 0.03} {-side} 0" {cam}/>
        </body>
      </body>
    </body>
    <body name="weight" pos="{anchor[0]} {anchor[1]} {anchor[2]}">
      {suspension}
      <geom name="string" type="capsule" fromto="0 0 0 0 0 -{cfg.string_length - 0.03}" size="0.001"
            mass="0.001" rgba="0.5 0.5 0.5 1" group="{GROUP_PENDULUM}"/>
      <geom name="weight" type="sphere" size="0.03" pos="0 0 -{cfg.string_length}" mass="0.5"
            rgba="0.05 0.05 0.05 1" group="{GROUP_PENDULUM}"/>
      <body name="apparatus" pos="0 0 -{cfg.string_length}">{cylinder}</body>
    </body>
  </worldbody>
  <actuator>
    <velocity name="pan" joint="pan" kv="5"/>
    <velocity name="tilt" joint="tilt" kv="2"/>
    <velocity name="left" joint="left" kv="0.5"/>
    <velocity name="right" joint="right" kv="0.5"/>
  </actuator>
</mujoco>
"""
