"""Test-wide settings and shared fixtures. Rendering is headless: MuJoCo picks its GL backend when first imported,
so MUJOCO_GL must be set before any test module imports mujoco: importing `pipeline` sets it (EGL here)."""

import pytest

import pipeline  # noqa: F401


@pytest.fixture(scope="session")
def sample_clip():
    """The bundled sample as `make_sample_clip` plans it (a few seconds to solve: made once for the
    SMPL and the G1 tests of the sample)."""
    from pipeline.human.sample import make_sample_clip

    return make_sample_clip()
