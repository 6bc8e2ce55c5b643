"""Video -> `HumanMotion`: MediaPipe Pose landmarks (in `.venv-video`), then an SMPL skeleton fit.

Steps:
  1. landmarks: `pipeline/human/video_landmarks.py` runs under the video venv's Python
     (`make video-venv`; override with $ADAMIMIC_VIDEO_PYTHON) and writes per-frame 33 metric
     world landmarks (hip-centred, camera-aligned axes: x right, y down, z away) and 2D image
     landmarks to an npz.
  2. clip: the longest run of frames with a detected person (gaps up to `MAX_GAP_FRAMES` are
     interpolated; a jump of the hip centre by more than `MAX_HIP_JUMP` of the image width
     means the tracker switched people and ends a run).
  3. camera assumption: a static pinhole camera, principal point at the image centre, square
     pixels, horizontal field of view `HFOV_DEG` = 60 degrees (focal length f = W / (2 tan 30°)).
     Per frame the hip centre's camera-frame position t solves, by linear least squares over the
     visible landmarks, u_k = f (X_k + t)_x / (X_k + t)_z + c_x (same for v): the metric 3D
     landmarks X_k fix the scale, so depth comes from the apparent size. Then, assuming a flat
     floor, each frame's hip is slid along its camera ray so the lowest foot meets the floor
     plane (`ground_depth`, median over 1.5 s so a jump's flight is kept).
  4. gravity: the camera may be pitched, so up is taken from the data: the mean over the clip of
     mid-ankle -> mid-shoulder is assumed vertical (people are upright on average). The camera
     frame is rotated so that direction is +z.
  5. fit: rotations of the SMPL skeleton (neutral shape scaled to the estimated height) by bone
     directions, top-down: pelvis from the hip line and the trunk; spine3 from the shoulder
     line and trunk, spine1/2 as slerps between; head from the ears and nose; each limb bone
     (hip->knee, knee->ankle, ankle->toe, shoulder->elbow, elbow->wrist) by the shortest
     rotation (no twist) from its rest direction to the observed one. The root translation puts
     the skeleton's hip midpoint on the recovered hip centre.
  6. smoothing: landmarks are smoothed with a Gaussian of `SMOOTH_LANDMARKS_S` seconds and the
     (noisier) recovered translation with `SMOOTH_TRANSLATION_S`.
  7. pipeline frame (z up, floor at 0, facing +x) as for every importer (`frames.py`).
Height: MediaPipe's landmarks are metric; the subject's height is the neutral body's scaled by
the ratio of the median observed leg + trunk length to the neutral skeleton's.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d, median_filter

from pipeline import REPO_ROOT
from pipeline.common import quat
from pipeline.common.errors import PipelineInputError
from pipeline.human import smpl
from pipeline.human.frames import MIN_DURATION_S, human_motion_from_smpl
from pipeline.human.motion import HumanMotion

VIDEO_VENV_PYTHON = REPO_ROOT / ".venv-video" / "bin" / "python"
LANDMARK_SCRIPT = Path(__file__).with_name("video_landmarks.py")
HFOV_DEG = 60.0
MAX_GAP_FRAMES = 3
MAX_HIP_JUMP = 0.08
MIN_VISIBILITY = 0.3
SMOOTH_LANDMARKS_S = 0.05
SMOOTH_TRANSLATION_S = 0.15
GROUND_WINDOW_S = 1.5
EXTRACT_TIMEOUT_S = 900

# MediaPipe Pose landmark indices.
MP = dict(
    nose=0, left_ear=7, right_ear=8, left_shoulder=11, right_shoulder=12, left_elbow=13, right_elbow=14,
    left_wrist=15, right_wrist=16, left_hip=23, right_hip=24, left_knee=25, right_knee=26,
    left_ankle=27, right_ankle=28, left_heel=29, right_heel=30, left_foot_index=31, right_foot_index=32,
)
J = {name: i for i, name in enumerate(smpl.SMPL_JOINT_NAMES)}
# (SMPL joint whose rotation moves the bone, SMPL child joint, MediaPipe start, MediaPipe end).
LIMB_BONES = [
    (f"{s}_{a}", f"{s}_{b}", f"{s}_{ma}", f"{s}_{mb}")
    for s in ("left", "right")
    for a, b, ma, mb in (
        ("hip", "knee", "hip", "knee"), ("knee", "ankle", "knee", "ankle"), ("ankle", "foot", "heel", "foot_index"),
        ("shoulder", "elbow", "shoulder", "elbow"), ("elbow", "wrist", "elbow", "wrist"),
    )
]


class VideoEnvironmentMissing(RuntimeError):
    """The optional video environment is not installed (`make video-venv`)."""


def video_python() -> Path:
    return Path(os.environ.get("ADAMIMIC_VIDEO_PYTHON", VIDEO_VENV_PYTHON))


def extract_landmarks(video: str | Path, out: str | Path) -> None:
    """Runs the MediaPipe extractor in the video venv; bad videos raise PipelineInputError."""
    python = video_python()
    if not python.exists():
        raise VideoEnvironmentMissing(f"{python} not found: run `make video-venv` to install the video extra")
    proc = subprocess.run(
        [str(python), str(LANDMARK_SCRIPT), str(video), str(out)],
        capture_output=True, text=True, timeout=EXTRACT_TIMEOUT_S,
        env={**os.environ, "GLOG_minloglevel": "2", "TF_CPP_MIN_LOG_LEVEL": "2"},
    )
    if proc.returncode == 3:
        raise PipelineInputError(video, None, proc.stderr.strip().splitlines()[-1].split(": ", 1)[-1])
    if proc.returncode != 0:
        raise RuntimeError(f"landmark extraction failed ({proc.returncode}): {proc.stderr[-2000:]}")


def load_video(path: str | Path, landmarks_npz: str | Path | None = None) -> HumanMotion:
    """Imports a video. `landmarks_npz` reuses an extractor output instead of running MediaPipe."""
    path = Path(path)
    if path.stat().st_size == 0:
        raise PipelineInputError(path, None, "empty video file")
    if landmarks_npz is None:
        with tempfile.TemporaryDirectory(prefix="adamimic-video-") as tmp:
            out = Path(tmp) / "landmarks.npz"
            extract_landmarks(path, out)
            with np.load(out) as data:
                marks = {k: data[k] for k in data.files}
    else:
        with np.load(landmarks_npz) as data:
            marks = {k: data[k] for k in data.files}
    return fit_landmarks(marks, source=str(path), name=path.stem)


# ------------------------------------------------------------------------------ clip selection
def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    runs, start = [], None
    for i, on in enumerate(list(mask) + [False]):
        if on and start is None:
            start = i
        elif not on and start is not None:
            runs.append((start, i))
            start = None
    return runs


def select_track(detected: np.ndarray, image: np.ndarray) -> tuple[int, int]:
    """[start, end) of the longest run of one tracked person (short gaps bridged)."""
    filled = detected.copy()
    for start, end in _runs(~detected):
        if start > 0 and end < len(detected) and end - start <= MAX_GAP_FRAMES:
            filled[start:end] = True
    hips = image[:, [MP["left_hip"], MP["right_hip"], MP["left_shoulder"], MP["right_shoulder"]], :2].mean(axis=1)
    breaks = np.zeros(len(detected), bool)
    idx = np.flatnonzero(detected)
    jumps = np.linalg.norm(np.diff(hips[idx], axis=0), axis=1) > MAX_HIP_JUMP * np.maximum(1, np.diff(idx))
    breaks[idx[1:][jumps]] = True
    best = (0, 0)
    for start, end in _runs(filled):
        cuts = [start] + [int(i) for i in np.flatnonzero(breaks[start:end]) + start if i > start] + [end]
        for a, b in zip(cuts[:-1], cuts[1:]):
            if b - a > best[1] - best[0]:
                best = (a, b)
    return best


def _bridge(values: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """Linear interpolation over undetected frames, per coordinate."""
    if detected.all():
        return values
    frames = np.arange(len(values))
    flat = values.reshape(len(values), -1)
    out = np.stack([np.interp(frames, frames[detected], col[detected]) for col in flat.T], axis=1)
    return out.reshape(values.shape)


# ------------------------------------------------------------------------------ camera
def hip_translation(world: np.ndarray, image: np.ndarray, vis: np.ndarray, width: int, height: int) -> np.ndarray:
    """Camera-frame hip centre (T, 3) per frame by least squares (see the module docstring)."""
    f = 0.5 * width / np.tan(np.radians(HFOV_DEG) / 2)
    cx, cy = 0.5 * width, 0.5 * height
    out = np.zeros((len(world), 3))
    for t in range(len(world)):
        w = np.clip(vis[t], 0.05, 1.0)
        u = image[t, :, 0] * width - cx
        v = image[t, :, 1] * height - cy
        x, y, z = world[t].T
        # f tx - u tz = u z - f x ;  f ty - v tz = v z - f y
        a = np.zeros((2 * len(u), 3))
        a[0::2, 0], a[0::2, 2] = f, -u
        a[1::2, 1], a[1::2, 2] = f, -v
        b = np.empty(2 * len(u))
        b[0::2] = u * z - f * x
        b[1::2] = v * z - f * y
        sw = np.repeat(np.sqrt(w), 2)
        out[t] = np.linalg.lstsq(a * sw[:, None], b * sw, rcond=None)[0]
    return out


def ground_depth(world: np.ndarray, hip_cam: np.ndarray, up: np.ndarray, fps: float) -> np.ndarray:
    """Rescales each frame's hip position along its camera ray so the lowest foot meets one floor.

    Depth from apparent size is noisy for small figures; a static camera over a flat floor gives a
    steadier cue: the floor plane (normal `up`, offset the median lowest-foot height of the
    size-based estimate) and the ray through the hip fix the depth. The per-frame scale is
    median-filtered over `GROUND_WINDOW_S` so a short flight phase (a jump) keeps its height.
    """
    feet = [MP[k] for k in ("left_ankle", "right_ankle", "left_heel", "right_heel", "left_foot_index", "right_foot_index")]
    foot_rel = np.min(world[:, feet] @ up, axis=1)  # lowest foot, relative to the hip, along up
    floor = np.median(foot_rel + hip_cam @ up)
    along = hip_cam @ up
    scale = np.where(np.abs(along) > 1e-3, (floor - foot_rel) / np.where(np.abs(along) > 1e-3, along, 1.0), 1.0)
    scale = np.where((scale > 0.2) & (scale < 5.0), scale, 1.0)  # a ray nearly parallel to the floor: keep size depth
    window = max(1, int(round(GROUND_WINDOW_S * fps))) | 1
    scale = median_filter(scale, size=window, mode="nearest")
    return hip_cam * scale[:, None]


# ------------------------------------------------------------------------------ fitting
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _frame_quat(left: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Orientation whose body axes (x left, y up, z front) match the given left/up (orthogonalised)."""
    y = _unit(up)
    x = _unit(left - np.sum(left * y, axis=-1, keepdims=True) * y)
    z = np.cross(x, y)
    return quat.from_matrix(np.stack([x, y, z], axis=-1))


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shortest rotation taking unit vectors a to b (..., 4)."""
    a, b = _unit(a), _unit(b)
    cross = np.cross(a, b)
    dot = np.sum(a * b, axis=-1, keepdims=True)
    q = np.concatenate([1.0 + dot, cross], axis=-1)
    # Opposite vectors: any perpendicular axis.
    opposite = (1.0 + dot[..., 0]) < 1e-9
    if np.any(opposite):
        perp = np.cross(a[opposite], np.array([1.0, 0.0, 0.0]))
        perp = np.where(np.linalg.norm(perp, axis=-1, keepdims=True) < 1e-6, np.cross(a[opposite], [0.0, 1.0, 0.0]), perp)
        q[opposite] = np.concatenate([np.zeros((perp.shape[0], 1)), _unit(perp)], axis=-1)
    return quat.normalize(q)


def estimate_height(world: np.ndarray) -> float:
    """Subject height from the median metric leg + trunk length against the neutral skeleton's."""
    def seg(a, b):
        return np.linalg.norm(world[:, MP[a]] - world[:, MP[b]], axis=-1)

    legs = 0.5 * (seg("left_hip", "left_knee") + seg("left_knee", "left_ankle")
                  + seg("right_hip", "right_knee") + seg("right_knee", "right_ankle"))
    mid_hip = 0.5 * (world[:, MP["left_hip"]] + world[:, MP["right_hip"]])
    mid_sh = 0.5 * (world[:, MP["left_shoulder"]] + world[:, MP["right_shoulder"]])
    observed = float(np.median(legs + np.linalg.norm(mid_sh - mid_hip, axis=-1)))
    r = smpl.NEUTRAL_REST_JOINTS
    neutral = 0.5 * (np.linalg.norm(r[1] - r[4]) + np.linalg.norm(r[4] - r[7]) + np.linalg.norm(r[2] - r[5])
                     + np.linalg.norm(r[5] - r[8])) + np.linalg.norm(0.5 * (r[16] + r[17]) - 0.5 * (r[1] + r[2]))
    return float(np.clip(smpl.NEUTRAL_HEIGHT * observed / neutral, 1.2, 2.2))


def fit_rotations(points: dict[str, np.ndarray], rest: np.ndarray) -> np.ndarray:
    """SMPL local axis-angles (T, 22, 3) from target points (name -> (T, 3), z-up world)."""
    frames = len(points["left_hip"])
    glob = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (frames, 22, 1))
    mid_hip = 0.5 * (points["left_hip"] + points["right_hip"])
    mid_sh = 0.5 * (points["left_shoulder"] + points["right_shoulder"])
    trunk = mid_sh - mid_hip
    # Rest-pose trunk is not exactly along +y; remove that small offset so an upright trunk fits upright.
    rest_trunk = 0.5 * (rest[16] + rest[17]) - 0.5 * (rest[1] + rest[2])
    rest_fix = quat.conjugate(_frame_quat(rest[1] - rest[2], rest_trunk))
    rest_fix_sh = quat.conjugate(_frame_quat(rest[16] - rest[17], rest_trunk))
    glob[:, J["pelvis"]] = quat.multiply(_frame_quat(points["left_hip"] - points["right_hip"], trunk), rest_fix)
    glob[:, J["spine3"]] = quat.multiply(_frame_quat(points["left_shoulder"] - points["right_shoulder"], trunk), rest_fix_sh)
    glob[:, J["spine3"]] = quat.make_continuous(glob[:, J["spine3"]])
    glob[:, J["spine1"]] = quat.slerp(glob[:, J["pelvis"]], glob[:, J["spine3"]], np.full(frames, 1 / 3))
    glob[:, J["spine2"]] = quat.slerp(glob[:, J["pelvis"]], glob[:, J["spine3"]], np.full(frames, 2 / 3))
    for collar in ("neck", "left_collar", "right_collar"):
        glob[:, J[collar]] = glob[:, J["spine3"]]
    ears_mid = 0.5 * (points["left_ear"] + points["right_ear"])
    head_up = ears_mid - mid_sh
    glob[:, J["head"]] = _frame_quat(points["left_ear"] - points["right_ear"], head_up)
    glob[:, J["neck"]] = quat.slerp(glob[:, J["spine3"]], glob[:, J["head"]], np.full(frames, 0.5))
    for joint, child, start, end in LIMB_BONES:
        parent = smpl.SMPL_PARENTS[J[joint]]
        rest_dir = quat.rotate(glob[:, parent], np.broadcast_to(rest[J[child]] - rest[J[joint]], (frames, 3)))
        glob[:, J[joint]] = quat.multiply(_swing(rest_dir, points[end] - points[start]), glob[:, parent])
    for leaf in ("left_foot", "right_foot", "left_wrist", "right_wrist"):
        glob[:, J[leaf]] = glob[:, smpl.SMPL_PARENTS[J[leaf]]]
    local = np.empty_like(glob)
    local[:, 0] = glob[:, 0]
    for j in range(1, 22):
        local[:, j] = quat.multiply(quat.conjugate(glob[:, smpl.SMPL_PARENTS[j]]), glob[:, j])
    return quat.to_axis_angle(local)


def fit_landmarks(marks: dict[str, np.ndarray], source: str, name: str) -> HumanMotion:
    """Turns the extractor's arrays into a `HumanMotion` (see the module docstring)."""
    for key in ("world", "image", "visibility", "detected", "fps", "width", "height"):
        if key not in marks:
            raise PipelineInputError(source, f"landmarks.{key}", "missing from the extractor output")
    fps = float(marks["fps"])
    if not np.isfinite(fps) or fps <= 0:
        raise PipelineInputError(source, "fps", f"the video reports a frame rate of {fps}")
    detected = np.asarray(marks["detected"], bool)
    if not detected.any():
        raise PipelineInputError(source, "person", f"no person detected in {len(detected)} frames")
    start, end = select_track(detected, marks["image"])
    if (end - start - 1) / fps < MIN_DURATION_S:
        raise PipelineInputError(
            source, "person",
            f"longest tracked stretch is {end - start} frames at {fps:g} fps, shorter than {MIN_DURATION_S:g} s",
        )
    det = detected[start:end]
    world = _bridge(marks["world"][start:end].astype(np.float64), det)
    image = _bridge(marks["image"][start:end].astype(np.float64), det)
    vis = _bridge(marks["visibility"][start:end].astype(np.float64), det)
    vis = np.where(vis >= MIN_VISIBILITY, vis, 0.05)
    sigma = SMOOTH_LANDMARKS_S * fps
    if sigma > 0.3:
        world = gaussian_filter1d(world, sigma, axis=0, mode="nearest")
        image = gaussian_filter1d(image, sigma, axis=0, mode="nearest")
    width, height_px = int(marks["width"]), int(marks["height"])
    hip_cam = hip_translation(world, image, vis, width, height_px)
    # Camera frame (x right, y down, z away) -> z-up, with "up" from the mean body axis.
    mid_ankle = 0.5 * (world[:, MP["left_ankle"]] + world[:, MP["right_ankle"]])
    mid_sh = 0.5 * (world[:, MP["left_shoulder"]] + world[:, MP["right_shoulder"]])
    up = _unit(np.mean(mid_sh - mid_ankle, axis=0))
    hip_cam = ground_depth(world, hip_cam, up, fps)
    hip_cam = gaussian_filter1d(hip_cam, max(SMOOTH_TRANSLATION_S * fps, 0.5), axis=0, mode="nearest")
    to_zup = _swing(up, np.array([0.0, 0.0, 1.0]))
    points = {k: quat.rotate(to_zup, world[:, i] + hip_cam) for k, i in MP.items()}

    subject_height = estimate_height(world)
    rest = smpl.rest_joints(height=subject_height)
    rotvec = fit_rotations(points, rest)
    pos, _ = smpl.forward_kinematics(rotvec, np.zeros((len(rotvec), 3)), rest)
    target_hip = 0.5 * (points["left_hip"] + points["right_hip"])
    trans = target_hip - 0.5 * (pos[:, J["left_hip"]] + pos[:, J["right_hip"]])
    return human_motion_from_smpl(
        local_rotvec=rotvec, trans=trans, betas=np.zeros(smpl.NUM_BETAS), fps=fps, source=source, name=name,
        up_axis="+z", rest=rest, height=subject_height,
    )
