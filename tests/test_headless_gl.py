"""Which offscreen GL the pipeline asks MuJoCo for, and a server with none (like the lent GPU machines,
which have no libEGL): training and evaluation import MuJoCo fine, and only rendering stops, with a
message that says what to install."""

import os
import subprocess
import sys

import pytest

import pipeline

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.parametrize("installed, expected", [({"EGL", "OSMesa"}, "egl"), ({"OSMesa"}, "osmesa"), (set(), "disable")])
def test_the_first_installed_gl_library_is_chosen(monkeypatch, installed, expected):
    monkeypatch.setattr(pipeline.ctypes.util, "find_library", lambda name: f"lib{name}.so" if name in installed else None)
    assert pipeline._headless_gl() == expected


def test_without_gl_mujoco_imports_and_rendering_fails_clearly():
    script = (
        "from pipeline.robot.g1 import build_model\n"
        "from pipeline.render.renderer import Renderer\n"
        "model = build_model(visual=True)\n"
        "print('imported')\n"
        "Renderer(model, 64, 48)\n"
    )
    env = dict(os.environ, MUJOCO_GL="disable")
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert "imported" in result.stdout
    assert result.returncode != 0
    assert "offscreen rendering failed with MUJOCO_GL=disable" in result.stderr
