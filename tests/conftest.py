"""Test-wide settings. Rendering is headless: MuJoCo picks its GL backend when first imported,
so MUJOCO_GL must be set before any test module imports mujoco."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
