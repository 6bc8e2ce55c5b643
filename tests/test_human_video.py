"""Video import: MediaPipe in .venv-video on a real clip (vtest.avi), and its bad inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline import REPO_ROOT
from pipeline.common.errors import PipelineInputError
from pipeline.human.importers import load_human_motion
from pipeline.human.video import fit_landmarks, video_python

VTEST = REPO_ROOT / ".cache" / "video" / "vtest.avi"
needs_venv = pytest.mark.skipif(not video_python().exists(), reason="video venv missing: run `make video-venv`")
needs_vtest = pytest.mark.skipif(not VTEST.is_file(), reason="vtest.avi missing: `make test` fetches it from opencv-doc")


@pytest.fixture(scope="module")
def vtest_marks(tmp_path_factory):
    """MediaPipe runs once per module (~12 s for vtest's 795 frames); the fits reuse its output."""
    if not (video_python().exists() and VTEST.is_file()):
        pytest.skip("video venv or vtest.avi missing")
    from pipeline.human.video import extract_landmarks

    marks = tmp_path_factory.mktemp("vtest") / "marks.npz"
    extract_landmarks(VTEST, marks)
    return marks


@pytest.fixture(scope="module")
def vtest_motion(vtest_marks):
    from pipeline.human.video import load_video

    return load_video(VTEST, landmarks_npz=vtest_marks)


@needs_venv
@needs_vtest
def test_vtest_pedestrian_imports(vtest_motion):
    m = vtest_motion
    assert m.fps == pytest.approx(10.0) and m.duration >= 1.0 and m.name == "vtest"
    pos = m.joint_pos
    assert np.all(np.isfinite(pos))
    # Upright: head above pelvis above ankles in most frames; feet on the floor on the whole.
    assert np.mean(pos[:, 15, 2] > pos[:, 0, 2] + 0.3) > 0.95
    assert np.mean(pos[:, 0, 2] > pos[:, [7, 8], 2].max(axis=1) + 0.4) > 0.9
    sole = pos[:, [7, 8, 10, 11], 2].min(axis=1)
    assert -0.05 < np.percentile(sole, 1) < 0.1 and np.median(sole) < 0.5
    # A pedestrian: an adult's height, walking pace (not teleporting), starting at the origin.
    assert 1.3 < m.height < 2.1
    speed = np.linalg.norm(np.diff(pos[:, 0, :2], axis=0), axis=1) * m.fps
    assert 0.3 < np.median(speed) < 3.0
    np.testing.assert_allclose(pos[0, 0, :2], 0.0, atol=1e-9)
    # Bone lengths are the skeleton's, constant in time (a rigid fit, not the raw landmarks).
    thigh = np.linalg.norm(pos[:, 4] - pos[:, 1], axis=1)
    assert np.ptp(thigh) < 1e-9


@needs_venv
@needs_vtest
def test_video_fit_is_deterministic(vtest_marks, vtest_motion):
    # Another MediaPipe pass would cost ~12 s; the fit (everything after the landmarks) runs again.
    from pipeline.human.video import load_video

    again = load_video(VTEST, landmarks_npz=vtest_marks)
    assert np.array_equal(again.joint_pos, vtest_motion.joint_pos)
    assert np.array_equal(again.local_rotvec, vtest_motion.local_rotvec)


def test_empty_video(tmp_path):
    path = tmp_path / "empty.mp4"
    path.write_bytes(b"")
    with pytest.raises(PipelineInputError, match="empty video"):
        load_human_motion(path)


@needs_venv
def test_unreadable_video(tmp_path):
    path = tmp_path / "broken.avi"
    path.write_bytes(b"this is not a video" * 100)
    with pytest.raises(PipelineInputError) as info:
        load_human_motion(path)
    assert str(path) in str(info.value)


@needs_venv
def test_video_without_a_person(tmp_path):
    cv2 = pytest.importorskip("cv2")
    path = tmp_path / "black.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120))
    for i in range(15):
        writer.write(np.full((120, 160, 3), 20 + i, np.uint8))
    writer.release()
    with pytest.raises(PipelineInputError, match="no person detected"):
        load_human_motion(path)


def _marks(frames=30, fps=10.0, detected=True):
    return {
        "world": np.zeros((frames, 33, 3)), "image": np.zeros((frames, 33, 3)), "visibility": np.zeros((frames, 33)),
        "detected": np.full(frames, detected), "fps": np.float64(fps), "width": np.int64(640), "height": np.int64(480),
    }


def test_landmark_bad_inputs_name_the_field():
    with pytest.raises(PipelineInputError, match="no person detected"):
        fit_landmarks(_marks(detected=False), "clip.mp4", "clip")
    with pytest.raises(PipelineInputError) as info:
        fit_landmarks(_marks(fps=0.0), "clip.mp4", "clip")
    assert info.value.field == "fps"
    short = _marks(frames=30)
    short["detected"][8:] = False
    with pytest.raises(PipelineInputError, match="shorter than 1 s"):
        fit_landmarks(short, "clip.mp4", "clip")
    broken = _marks()
    del broken["world"]
    with pytest.raises(PipelineInputError, match="landmarks.world"):
        fit_landmarks(broken, "clip.mp4", "clip")
