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

from wfnn_common.config import check_fields

JOINTS = ("pan", "tilt", "left", "right")
"""Joint names in model order."""
CAMERAS = ("left", "right")
N_DISCS = 4
WEIGHT_MASS, STRING_MASS, CYLINDER_MASS = 0.5, 0.001, 0.05
"""Masses of the hanging parts (kg)."""

# Geom groups, so rays (the camera's line of sight) and renders can leave the pendulum or the
# discs out.
GROUP_HEAD, GROUP_PENDULUM, GROUP_SCENE, GROUP_DISCS = 0, 1, 2, 3


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
    weight_radius: float = 0.03
    """Radius of the lead weight (m); the discs on the board look the same size from the head."""
    disc_height: float = -0.12
    """Height of the training apparatus' discs on the board (m): below the weight, in view, and
    behind the cylinder's path."""
    disc_spacing: float = 0.15
    """Horizontal spacing of the apparatus' discs (m)."""
    elastic: bool = False
    """Hang the weight on elastic (3D motion) instead of string (planar swing)."""
    elastic_stiffness: float = 60.0
    """N/m of the elastic."""
    apparatus: bool = True
    """Hang the white cylinder below the weight (it hides static targets as it swings past)."""
    image_size: tuple[int, int] = (320, 240)
    """Largest camera image rendered (width, height)."""
    timestep: float = 1.0 / (15 * 33)
    """Physics step (s): 33 steps per 15 Hz control tick."""

    def __post_init__(self) -> None:
        check_fields(self)


def _joint(name: str, axis: str, limit_deg: float, armature: float) -> str:
    return (
        f'<joint name="{name}" type="hinge" axis="{axis}" range="-{limit_deg} {limit_deg}" '
        f'limited="true" armature="{armature}" damping="0"/>'
    )


def disc_y(cfg: HydraModelConfig, i: int) -> float:
    """Horizontal position of the apparatus' disc i on the board (m), centred on the head."""
    return cfg.disc_spacing * (1.5 - i)


def hydra_mjcf(cfg: HydraModelConfig, limits_deg: dict[str, float]) -> str:
    """The MJCF text of the head and the apparatus."""
    half = cfg.baseline / 2
    fwd, side = cfg.camera_offset
    # MuJoCo cameras look along their -z with +y up: x_cam = world -y, y_cam = world +z.
    cam = f'xyaxes="0 -1 0 0 0 1" fovy="{cfg.fovy_deg}"'
    anchor = (cfg.target_distance, 0.0, cfg.string_length)
    if cfg.elastic:
        # The elastic's rest length puts the weight at the cameras' height when it hangs still,
        # as the experimenter would hang it.
        hanging = WEIGHT_MASS + STRING_MASS + (CYLINDER_MASS if cfg.apparatus else 0.0)
        springref = -hanging * 9.81 / cfg.elastic_stiffness
        suspension = (
            '<joint name="swing_x" type="hinge" axis="1 0 0" damping="0.002"/>'
            '<joint name="swing_y" type="hinge" axis="0 1 0" damping="0.002"/>'
            f'<joint name="stretch" type="slide" axis="0 0 -1" stiffness="{cfg.elastic_stiffness}" '
            f'springref="{springref:.6f}" damping="0.05" range="-0.3 0.6" limited="true"/>'
        )
    else:
        suspension = '<joint name="swing_x" type="hinge" axis="1 0 0" damping="0.0005"/>'
    cylinder = (
        '<geom name="cylinder" type="cylinder" size="0.025 0.1" pos="0 0 -0.16" rgba="1 1 1 1" '
        f'mass="{CYLINDER_MASS}" group="{GROUP_PENDULUM}"/>'
        if cfg.apparatus
        else ""
    )
    # Discs as large in the image as the weight, so one template matches both (Section 7.5.2).
    camera_x = fwd + 0.03
    board = cfg.board_distance - 0.01
    disc_radius = cfg.weight_radius * (board - camera_x) / (cfg.target_distance - camera_x)
    discs = "\n".join(
        f'<body name="disc{i}" mocap="true" pos="{board} {disc_y(cfg, i)} {cfg.disc_height}">'
        f'<geom name="disc{i}" type="cylinder" size="{disc_radius:.4f} 0.002" euler="0 90 0" rgba="0 0 0 1" '
        f'contype="0" conaffinity="0" group="{GROUP_DISCS}"/></body>'
        for i in range(N_DISCS)
    )
    head_body = 'gravcomp="1"'
    width, height = cfg.image_size
    return f"""
<mujoco model="hydra">
  <option timestep="{cfg.timestep}" integrator="implicitfast"/>
  <visual><global offwidth="{max(640, width)}" offheight="{max(480, height)}"/></visual>
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
          <camera name="left" pos="{camera_x} {side} 0" {cam}/>
        </body>
        <body name="right_link" pos="0 {-half} 0" {head_body}>
          {_joint("right", "0 0 1", limits_deg["right"], 0.005)}
          <geom type="box" size="0.03 0.02 0.02" pos="{fwd} {-side} 0" mass="0.2" group="{GROUP_HEAD}"/>
          <camera name="right" pos="{camera_x} {-side} 0" {cam}/>
        </body>
      </body>
    </body>
    <body name="weight" pos="{anchor[0]} {anchor[1]} {anchor[2]}">
      {suspension}
      <geom name="string" type="capsule" fromto="0 0 0 0 0 -{cfg.string_length - 0.03}" size="0.001"
            mass="{STRING_MASS}" rgba="0.5 0.5 0.5 1" group="{GROUP_PENDULUM}"/>
      <geom name="weight" type="sphere" size="{cfg.weight_radius}" pos="0 0 -{cfg.string_length}"
            mass="{WEIGHT_MASS}" rgba="0.05 0.05 0.05 1" group="{GROUP_PENDULUM}"/>
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
