"""Shared test setup.

`sims` chooses MuJoCo's off-screen GL backend (MUJOCO_GL), which must happen before `mujoco` is
first imported; a test module that imports `mujoco` before `sims` would otherwise leave MuJoCo on
its display backend, and every rendering test after it would skip.
"""

import sims  # noqa: F401
