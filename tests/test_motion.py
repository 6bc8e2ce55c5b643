"""Motion datasets: exact write -> read round trip, FK consistency of stored poses, bad input."""

import json
import shutil

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.motion import Motion, RobotKinematics
from pipeline.motion.dataset import read_motions, write_motions

FIELDS = ("root_pos", "root_quat", "joint_pos", "body_pos", "body_quat")


@pytest.fixture(scope="module")
def kin():
    return RobotKinematics()


def _motion(kin, frames, seed, name):
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 50.0
    root_pos = np.stack([0.3 * t, 0.05 * np.sin(3 * t), 0.78 + 0.02 * np.cos(5 * t)], axis=1)
    yaw = 0.4 * t
    root_quat = np.stack([np.cos(yaw / 2), 0.02 * np.sin(t), 0 * t, np.sin(yaw / 2)], axis=1)
    joints = kin.config.default_joint_pos + 0.3 * np.sin(t[:, None] * rng.uniform(1, 4, 27) + rng.uniform(0, 6, 27))
    return kin.motion(50.0, root_pos, root_quat, joints, name=name)


@pytest.fixture(scope="module")
def motions(kin):
    return [_motion(kin, 40, 0, "walk forward"), _motion(kin, 23, 1, "turn left")]


def test_round_trip_is_exact(tmp_path, motions):
    path = tmp_path / "motions"
    write_motions(path, motions, extra={"note": "test"})
    back = read_motions(path)
    assert len(back) == 2
    for a, b in zip(motions, back):
        assert b.name == a.name and b.fps == a.fps
        assert b.joint_names == a.joint_names and b.body_names == a.body_names
        for key in FIELDS:
            got, want = getattr(b, key), getattr(a, key)
            assert got.dtype == np.float64 and got.shape == want.shape
            assert np.array_equal(got, want), key  # bit-exact, not approximately equal
    info = json.loads((path / "meta/info.json").read_text())
    assert info["features"]["joint_pos"]["names"] == list(motions[0].joint_names)
    assert info["features"]["body_quat"]["names"] == list(motions[0].body_names)
    assert info["features"]["body_pos"]["shape"] == [17, 3]
    assert json.loads((path / "meta/pipeline.json").read_text()) == {"note": "test"}


def test_single_motion_save_load(tmp_path, motions):
    motions[0].save(tmp_path / "one")
    loaded = Motion.load(tmp_path / "one")
    assert np.array_equal(loaded.body_pos, motions[0].body_pos)
    with pytest.raises(PipelineInputError, match="episodes"):
        write_motions(tmp_path / "two", motions)
        Motion.load(tmp_path / "two")


def test_fk_of_stored_root_and_joints_reproduces_stored_body_poses(tmp_path, kin, motions):
    write_motions(tmp_path / "m", motions)
    for motion in read_motions(tmp_path / "m"):
        pos, rot = kin.body_poses(motion.root_pos, motion.root_quat, motion.joint_pos)
        np.testing.assert_allclose(pos, motion.body_pos, atol=1e-12)
        # q and -q are one rotation
        assert np.max(1 - np.abs(np.sum(rot * motion.body_quat, axis=-1))) < 1e-12
        # the stored poses really move: a wrong FK would not pass by accident
        assert np.ptp(motion.body_pos[:, motion.body_index("left_wrist"), 0]) > 0.05


def test_velocities_survive_the_round_trip(tmp_path, motions):
    write_motions(tmp_path / "m", motions[:1])
    back = read_motions(tmp_path / "m")[0]
    np.testing.assert_array_equal(back.joint_vel, motions[0].joint_vel)
    np.testing.assert_array_equal(back.root_ang_vel, motions[0].root_ang_vel)


def test_mismatched_motions_are_refused_and_nothing_written(tmp_path, kin, motions):
    target = tmp_path / "m"
    other_rate = motions[1].resample(30.0)
    with pytest.raises(PipelineInputError, match="fps"):
        write_motions(target, [motions[0], other_rate])
    fewer = motions[1].reorder_joints(motions[1].joint_names[:-1])
    with pytest.raises(PipelineInputError, match="joint_names"):
        write_motions(target, [motions[0], fewer])
    with pytest.raises(PipelineInputError, match="motions"):
        write_motions(target, [])
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []  # no staging directory left behind


def test_bad_motion_values_leave_existing_dataset_unchanged(tmp_path, motions):
    target = tmp_path / "m"
    write_motions(target, motions[:1])
    before = {p: p.read_bytes() for p in sorted(target.rglob("*")) if p.is_file()}
    broken = motions[1]
    broken.joint_pos = broken.joint_pos.copy()
    broken.joint_pos[3, 5] = np.nan
    try:
        with pytest.raises(PipelineInputError, match="joint_pos"):
            write_motions(target, [motions[0], broken])
    finally:
        broken.joint_pos[3, 5] = 0.0
    after = {p: p.read_bytes() for p in sorted(target.rglob("*")) if p.is_file()}
    assert after == before


def test_read_rejects_a_dataset_without_motion_features(tmp_path):
    from pipeline.dataset.lerobot import Feature, write_dataset

    write_dataset(tmp_path / "d", fps=50, features={"x": Feature("float64", (2,))},
                  episodes=[{"x": np.zeros((3, 2))}], tasks=["t"])
    with pytest.raises(PipelineInputError, match="features.root_pos"):
        read_motions(tmp_path / "d")


def test_read_rejects_wrong_joint_names(tmp_path, motions):
    write_motions(tmp_path / "m", motions[:1])
    info_path = tmp_path / "m/meta/info.json"
    info = json.loads(info_path.read_text())
    info["features"]["joint_pos"]["names"] = info["features"]["joint_pos"]["names"][:5]
    info_path.write_text(json.dumps(info))
    with pytest.raises(PipelineInputError, match="joint_pos.names"):
        read_motions(tmp_path / "m")


def test_fps_must_be_positive(tmp_path, motions):
    write_motions(tmp_path / "m", motions[:1])
    info_path = tmp_path / "m/meta/info.json"
    info = json.loads(info_path.read_text())
    info["fps"] = 0
    info_path.write_text(json.dumps(info))
    with pytest.raises(PipelineInputError, match="fps") as err:
        read_motions(tmp_path / "m")
    assert "info.json" in str(err.value)
    shutil.rmtree(tmp_path / "m")
