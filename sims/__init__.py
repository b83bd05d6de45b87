"""Simulated tasks for wfnn, behind one vectorised task interface (`sims.base.VecTask`).

- In numpy: the boat, cart-pole and 1-DOF positioning (thesis Ch 3-4, App A).
- On MuJoCo: the HyDrA active head (`sims.hydra`) and the Nomad 200 (`sims.nomad`), with their
  rendered cameras.
- Any Gymnasium task with Box spaces (`sims.gym`).

MuJoCo's GL backend is fixed when `mujoco` is imported. With no display the default (GLFW)
cannot render, and a backend whose libraries are missing makes the import itself fail, so unless
MUJOCO_GL is already set it is set here to the first off-screen backend whose libraries load
(EGL, then OSMesa); with neither, rendering is reported unavailable and everything else works.
"""

import ctypes
import os
import sys


def _loads(*names: str) -> bool:
    """Whether any of these shared libraries loads."""
    for name in names:
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


if "MUJOCO_GL" not in os.environ and sys.platform.startswith("linux"):
    if _loads("libEGL.so.1") and _loads("libOpenGL.so.0", "libGL.so.1"):
        os.environ["MUJOCO_GL"] = "egl"
    elif _loads("libOSMesa.so.8", "libOSMesa.so.6"):
        os.environ["MUJOCO_GL"] = "osmesa"
