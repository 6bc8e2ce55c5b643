"""AdaMimic pipeline: human motion in, deployable Unitree G1 policy out."""

import ctypes.util
import os
from pathlib import Path


def _headless_gl() -> str:
    """MuJoCo's offscreen GL: EGL where libEGL is installed, else OSMesa, else "disable", which keeps
    `import mujoco` working on a server without either (MUJOCO_GL=egl there makes PyOpenGL raise an
    AttributeError that MuJoCo does not catch, which would stop even the stages that never render);
    the stages that do render then stop with their own message (pipeline/render/renderer.py)."""
    for library, backend in (("EGL", "egl"), ("OSMesa", "osmesa")):
        if ctypes.util.find_library(library):
            return backend
    return "disable"


# Headless by default (stages render previews and videos); MuJoCo reads this when first imported.
os.environ.setdefault("MUJOCO_GL", _headless_gl())

# The same CPU kernels on every x86-64 machine (AVX2 + FMA), so the same inputs give the same bytes:
# set before numpy and torch load (every stage script imports `pipeline` first). Why and how:
# pipeline/common/cpu_kernels.py.
from pipeline.common.cpu_kernels import pin_cpu_kernels  # noqa: E402

pin_cpu_kernels()

REPO_ROOT = Path(__file__).resolve().parent.parent
