"""The balance policy's recorded starts (pipeline/balance/starts.py): states moved onto flat ground, and the
file they are written to."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from pipeline.balance.starts import _on_flat_ground, load_start_states
from pipeline.common.errors import PipelineInputError


def _ledge_model() -> mujoco.MjModel:
    """The G1 on a floor with a 0.2 m high box from x = 1 to 2."""
    from pipeline.robot.g1 import build_spec

    def ledge(spec):
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1])
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.5, 1.0, 0.1], pos=[1.5, 0.0, 0.1])

    return build_spec(terrain=ledge, visual=False).compile()


def test_a_state_keeps_its_height_above_the_ground_it_is_judged_on():
    from pipeline.robot.g1 import default_qpos

    model = _ledge_model()
    qpos = default_qpos()
    qpos[0:3] = [1.5, 0.3, 0.95]  # over the box, 0.75 m above its top
    flat = _on_flat_ground(model, qpos, max_tilt=0.8, min_height=0.4)
    assert flat[0] == flat[1] == 0.0 and flat[2] == pytest.approx(0.75)
    # a robot handed over above a ledge it is about to step off lands on the floor the reference ends on
    assert _on_flat_ground(model, qpos, 0.8, 0.4, ground=0.0)[2] == pytest.approx(0.95)
    assert np.array_equal(flat[3:], qpos[3:])
    low = qpos.copy()
    low[2] = 0.5  # 0.3 m above the box: past the 0.4 m height check
    assert _on_flat_ground(model, low, 0.8, 0.4) is None
    tilted = qpos.copy()
    tilted[3:7] = [np.cos(0.6), np.sin(0.6), 0.0, 0.0]  # 69° about x
    assert _on_flat_ground(model, tilted, 0.8, 0.4) is None


def test_a_start_state_file_without_velocities_is_refused(tmp_path):
    path = tmp_path / "starts.npz"
    np.savez(path, qpos=np.zeros((2, 34)))
    with pytest.raises(PipelineInputError, match="qvel"):
        load_start_states(path)
    assert load_start_states(tmp_path / "absent.npz") is None
