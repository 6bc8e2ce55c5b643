"""Importers of human clips: the shared AMASS-style npz (real data), GVHMR .pt, bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.common import quat
from pipeline.common.errors import PipelineInputError
from pipeline.human import smpl
from pipeline.human.importers import load_human_motion

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "adamimic_smpl"
NAMES = ("far_jump", "high_jump", "jump_step_down", "jump_step_up", "tennis_hit")
needs_shared = pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data/adamimic_smpl not present")


@pytest.fixture(scope="module")
def motions():
    return {name: load_human_motion(SHARED / f"{name}.npz") for name in NAMES} if SHARED.is_dir() else {}


def _sole(m):
    return m.joint_pos[:, [7, 8, 10, 11], 2].min(axis=1)


@needs_shared
@pytest.mark.parametrize("name", NAMES)
def test_shared_clip_imports_upright_on_the_floor_facing_x(motions, name):
    m = motions[name]
    assert m.fps == 30.0 and m.num_frames > 60 and m.name == name
    pos = m.joint_pos
    # z-up: head above pelvis above ankles in (nearly) every frame.
    assert np.mean(pos[:, 15, 2] > pos[:, 0, 2]) > 0.95
    assert np.mean(pos[:, 0, 2] > pos[:, [7, 8], 2].max(axis=1)) > 0.95
    # Feet on the floor: the lowest foot joint sits a few cm above z = 0 (the sole), not below.
    assert 0.0 < np.percentile(_sole(m), 1) < 0.06
    assert np.percentile(_sole(m), 10) < 0.10
    # Starts at the origin, facing +x.
    np.testing.assert_allclose(pos[0, 0, :2], 0.0, atol=1e-9)
    front = quat.rotate(m.joint_quat[:5, 0], smpl.BODY_FRONT).mean(axis=0)
    assert front[0] / np.linalg.norm(front[:2]) > 0.97
    assert 1.5 < m.height < 1.95


@needs_shared
def test_far_jump_travels_forward_along_x(motions):
    pelvis = motions["far_jump"].joint_pos[:, 0]
    travel = pelvis[-1] - pelvis[0]
    assert travel[0] > 2.0 and abs(travel[1]) < 0.3 * travel[0]


@needs_shared
def test_smpl_formula_holds_in_the_new_frame(motions):
    m = motions["far_jump"]
    rest = smpl.rest_joints(m.betas)
    pos, rot = smpl.forward_kinematics(m.local_rotvec, m.root_trans, rest)
    np.testing.assert_allclose(pos, m.joint_pos, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(rot * m.joint_quat, axis=-1)), 1.0, atol=1e-9)


def _to_y_up(poses66: np.ndarray, trans: np.ndarray, betas: np.ndarray, yaw: float):
    """Re-expresses a z-up clip in a y-up source frame (plus a yaw), the SMPL way."""
    j0 = smpl.rest_joints(betas)[0]
    # z-up -> y-up is -90 degrees about x (y -> -z, z -> y); then an arbitrary heading about y.
    c = quat.multiply(quat.from_axis_angle(np.array([0.0, yaw, 0.0])), quat.from_axis_angle(np.array([-np.pi / 2, 0, 0])))
    poses = poses66.reshape(-1, 22, 3).astype(np.float64).copy()
    poses[:, 0] = quat.to_axis_angle(quat.multiply(c, quat.from_axis_angle(poses[:, 0])))
    return poses.reshape(-1, 66), quat.rotate(c, j0 + trans) - j0


@needs_shared
def test_y_up_source_gives_the_same_motion(tmp_path, motions):
    data = np.load(SHARED / "far_jump.npz")
    poses, trans = _to_y_up(data["poses"], data["trans"].astype(np.float64), data["betas"], yaw=2.0)
    path = tmp_path / "far_jump_yup.npz"
    np.savez(path, poses=poses, trans=trans, betas=data["betas"], mocap_framerate=30.0)
    again = load_human_motion(path)
    np.testing.assert_allclose(again.joint_pos, motions["far_jump"].joint_pos, atol=2e-5)


@needs_shared
def test_gvhmr_pt_matches_the_npz(tmp_path, motions):
    torch = pytest.importorskip("torch")
    data = np.load(SHARED / "far_jump.npz")
    poses, trans = _to_y_up(data["poses"], data["trans"].astype(np.float64), data["betas"], yaw=-1.0)
    frames = poses.shape[0]
    results = {
        "smpl_params_global": {
            "global_orient": torch.tensor(poses[:, :3], dtype=torch.float32),
            "body_pose": torch.tensor(poses[:, 3:66], dtype=torch.float32),
            "betas": torch.tensor(np.repeat(data["betas"][None], frames, 0), dtype=torch.float32),
            "transl": torch.tensor(trans, dtype=torch.float32),
        }
    }
    run = tmp_path / "far_jump_run"
    run.mkdir()
    torch.save(results, run / "hmr4d_results.pt")
    m = load_human_motion(run / "hmr4d_results.pt")
    assert m.name == "far_jump_run" and m.fps == 30.0
    np.testing.assert_allclose(m.joint_pos, motions["far_jump"].joint_pos, atol=1e-4)
    del results["smpl_params_global"]["transl"]
    torch.save(results, run / "hmr4d_results.pt")
    with pytest.raises(PipelineInputError, match="smpl_params_global.transl"):
        load_human_motion(run / "hmr4d_results.pt")


@needs_shared
def test_import_is_deterministic():
    a = load_human_motion(SHARED / "tennis_hit.npz")
    b = load_human_motion(SHARED / "tennis_hit.npz")
    for key in ("joint_pos", "joint_quat", "local_rotvec", "root_trans", "betas"):
        assert np.array_equal(getattr(a, key), getattr(b, key))


# --- bad input -------------------------------------------------------------------------------

def _good_arrays(frames: int = 40, fps: float = 30.0) -> dict:
    poses = np.zeros((frames, 66))
    poses[:, 0] = np.pi / 2  # a z-up AMASS body standing upright
    trans = np.zeros((frames, 3))
    trans[:, 0] = np.linspace(0, 1, frames)
    return {"poses": poses, "trans": trans, "betas": np.zeros(10), "mocap_framerate": np.array(fps)}


def _write(tmp_path, **changes) -> Path:
    arrays = _good_arrays()
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    path = tmp_path / "clip.npz"
    np.savez(path, **arrays)
    return path


def test_good_synthetic_npz_loads(tmp_path):
    m = load_human_motion(_write(tmp_path))
    assert m.num_frames == 40
    assert m.joint_pos[0, 15, 2] > 1.3  # upright, head up


@pytest.mark.parametrize(
    "changes, field, words",
    [
        ({"poses": None}, "poses", "missing"),
        ({"trans": None}, "trans", "missing"),
        ({"mocap_framerate": None}, "mocap_framerate", "missing"),
        ({"poses": np.zeros((40, 60))}, "poses", "shape"),
        ({"trans": np.zeros((39, 3))}, "trans", "shape"),
        ({"mocap_framerate": np.array(0.0)}, "fps", "positive"),
        ({"mocap_framerate": np.array(-30.0)}, "fps", "positive"),
        ({"poses": np.full((40, 66), np.nan)}, "poses", "NaN"),
        ({"trans": np.full((40, 3), np.inf)}, "trans", "NaN"),
        ({"betas": np.array([np.nan] * 10)}, "betas", "NaN"),
    ],
)
def test_bad_npz_names_file_and_field(tmp_path, changes, field, words):
    path = _write(tmp_path, **changes)
    with pytest.raises(PipelineInputError) as info:
        load_human_motion(path)
    assert info.value.field == field and words in info.value.problem
    assert str(path) in str(info.value)


def test_short_clip_is_rejected(tmp_path):
    arrays = _good_arrays(frames=25)
    path = tmp_path / "short.npz"
    np.savez(path, **arrays)
    with pytest.raises(PipelineInputError, match="shorter than 1 s"):
        load_human_motion(path)


@pytest.mark.parametrize("suffix, content", [(".npz", b"not a zip"), (".pt", b"\x00garbage"), (".npz", b"")])
def test_unreadable_files(tmp_path, suffix, content):
    path = tmp_path / f"broken{suffix}"
    path.write_bytes(content)
    with pytest.raises(PipelineInputError, match="cannot read"):
        load_human_motion(path)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(PipelineInputError, match="not found"):
        load_human_motion(tmp_path / "nope.npz")
    (tmp_path / "clip.bvh").write_text("HIERARCHY")
    with pytest.raises(PipelineInputError, match="unknown file type"):
        load_human_motion(tmp_path / "clip.bvh")
