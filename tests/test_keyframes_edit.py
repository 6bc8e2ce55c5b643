"""f_edit / D_rule: local motion untouched, offsets exactly ψ-consistent, D_rule continuous and equal
to D_edit at keyframes; datasets round-trip; the figure and video get written."""

import numpy as np
import pytest

from pipeline.keyframes.config import TaskConfig
from pipeline.keyframes.datasets import frame_offsets, load_tracking_data, write_tracking_dataset
from pipeline.keyframes.edit import apply_offsets, build_tracking_data, sample_psi
from pipeline.keyframes.select import select_keyframes
from pipeline.keyframes.synthetic import Flight, synthetic_jump_motion

FAR = {"raw": 1.1, "easy": [[0.7, 1.6]], "hard": [[0.2, 0.7], [1.6, 2.0]]}


def _setup(edit, psi, flights, sign=1, **kw):
    task = TaskConfig.from_dict("t", {"input": "x.npz", "edit": {"mode": edit, "sign": sign, **kw.pop("edit_kw", {})},
                                      "psi": psi, **kw})
    motion = synthetic_jump_motion(flights, duration=3.0, hit_time=kw.get("hit_time_", None) or 2.3)
    table = select_keyframes(motion, task)
    return motion, task, table


@pytest.fixture(scope="module")
def far():
    motion, task, table = _setup("x", FAR, [Flight(1.0, 0.4, 1.1)], terrain="gap")
    return motion, task, table, build_tracking_data(motion, task, table, "edit", 24), \
        build_tracking_data(motion, task, table, "rule", 24)


def test_local_motion_identical_across_all_edited_motions(far):
    motion, _, _, edit, rule = far
    for data in (edit, rule):
        for off in frame_offsets(data):
            edited = apply_offsets(motion, off)
            np.testing.assert_array_equal(edited.joint_pos, motion.joint_pos)
            np.testing.assert_array_equal(edited.root_quat, motion.root_quat)
            np.testing.assert_array_equal(edited.body_quat, motion.body_quat)
            # bodies relative to the root: unchanged up to float rounding of the shared translation
            np.testing.assert_allclose(edited.body_pos - edited.root_pos[:, None], motion.body_pos - motion.root_pos[:, None],
                                       atol=1e-12)


def test_far_jump_offsets_exactly_psi(far):
    _, _, table, edit, _ = far
    landing = list(table.labels).index("landing")
    expected = edit.psi - 1.1
    np.testing.assert_allclose(edit.keyframe_offsets[:, landing, 0], expected, atol=1e-15)
    np.testing.assert_array_equal(edit.keyframe_offsets[:, :landing], 0.0)  # before: untouched
    np.testing.assert_allclose(edit.keyframe_offsets[:, landing:, 0], expected[:, None] * np.ones(len(table) - landing))
    np.testing.assert_array_equal(edit.keyframe_offsets[..., 1:], 0.0)


def test_rule_continuous_and_equal_to_edit_at_keyframes(far):
    motion, _, table, edit, rule = far
    np.testing.assert_array_equal(rule.keyframe_offsets, edit.keyframe_offsets)
    np.testing.assert_array_equal(rule.dense_offsets[:, table.frames], edit.keyframe_offsets)
    step = np.abs(np.diff(rule.dense_offsets, axis=1)).max(axis=(1, 2))  # per sample
    span = np.abs(edit.psi - 1.1)
    root_step = np.abs(np.diff(motion.root_pos[:, 0])).max()
    flight = np.ptp(motion.root_pos[:, 0])
    # each frame adds at most its share of root progress: no jumps
    assert np.all(step <= span * root_step / flight * 1.0001 + 1e-12)
    # monotone along x from the takeoff to the landing, then held
    takeoff, landing = table.frames[list(table.labels).index("takeoff")], table.frames[list(table.labels).index("landing")]
    d = np.diff(rule.dense_offsets[:, takeoff:landing + 1, 0], axis=1) * np.sign(edit.psi - 1.1)[:, None]
    assert np.all(d >= -1e-12)
    assert np.all(rule.dense_offsets[:, landing:] == rule.dense_offsets[:, landing:landing + 1])
    assert np.all(rule.dense_offsets[:, :takeoff + 1] == 0.0)


def test_triple_jump_cumulative_split():
    flights = [Flight(0.6, 0.3, 0.8), Flight(1.2, 0.3, 0.7), Flight(1.8, 0.4, 0.9)]
    motion, task, table = _setup("x", {"raw": 2.4, "easy": [[1.65, 3.15]], "hard": [[1.2, 1.65], [3.15, 4.2]]}, flights)
    data = build_tracking_data(motion, task, table, "edit", 9)
    labels = list(table.labels)
    delta = data.psi - 2.4
    for k in (1, 2, 3):
        np.testing.assert_allclose(data.keyframe_offsets[:, labels.index(f"landing_{k}"), 0], delta * k / 3, atol=1e-12)
    np.testing.assert_allclose(data.keyframe_offsets[:, -1, 0], delta, atol=1e-12)
    # the takeoff of jump k+1 sits with landing k
    np.testing.assert_allclose(data.keyframe_offsets[:, labels.index("takeoff_2"), 0], delta / 3, atol=1e-12)


def test_high_jump_apex_only_then_back():
    motion, task, table = _setup("z_apex", {"raw": 0.2, "easy": [[0.1, 0.35]], "hard": [[0.05, 0.1], [0.35, 0.6]]},
                                 [Flight(1.0, 0.5, 0.1)])
    data = build_tracking_data(motion, task, table, "rule", 8)
    apex = list(table.labels).index("apex")
    np.testing.assert_allclose(data.keyframe_offsets[:, apex, 2], data.psi - 0.2, atol=1e-15)
    off = data.keyframe_offsets.copy()
    off[:, apex] = 0
    np.testing.assert_array_equal(off, 0.0)
    np.testing.assert_array_equal(data.dense_offsets[:, table.frames[apex + 1]:], 0.0)  # back after the apex


def test_step_down_holds_lower_height():
    motion, task, table = _setup("z_hold", {"raw": 0.2, "easy": [[0.05, 0.25]], "hard": [[0.25, 0.5]]},
                                 [Flight(1.0, 0.34, 0.4, -0.2)], sign=-1, terrain="step")
    data = build_tracking_data(motion, task, table, "edit", 6)
    landing = list(table.labels).index("landing")
    np.testing.assert_allclose(data.keyframe_offsets[:, landing:, 2], -(data.psi - 0.2)[:, None] * np.ones(len(table) - landing))


def test_heading_and_lateral_directions():
    heading = 0.6
    task = TaskConfig.from_dict("b", {"input": "x.npz", "edit": "heading", "psi": {"raw": 1.3, "easy": [[1.3, 1.9]]},
                                      "keyframes": {"events": ["takeoff", "landing", "hit"]}})
    motion = synthetic_jump_motion([Flight(0.8, 0.3, 0.6)], duration=3.0, heading=heading, hit_time=2.0)
    data = build_tracking_data(motion, task, select_keyframes(motion, task), "edit", 4)
    hit = list(data.keyframe_labels).index("hit")
    off = data.keyframe_offsets[:, hit]
    np.testing.assert_allclose(off[:, :2], (data.psi - 1.3)[:, None] * [np.cos(heading), np.sin(heading)], atol=1e-12)
    tennis = TaskConfig.from_dict("t", {"input": "x.npz", "edit": "y", "psi": {"raw": 1.0, "easy": [[0.8, 1.2]]},
                                        "keyframes": {"events": ["hit"]}})
    data = build_tracking_data(motion, tennis, select_keyframes(motion, tennis), "edit", 4)
    hit = list(data.keyframe_labels).index("hit")
    np.testing.assert_allclose(data.keyframe_offsets[:, hit], np.column_stack([0 * data.psi, data.psi - 1.0, 0 * data.psi]))


def test_psi_samples_cover_train_range_deterministically():
    s = sample_psi([(0.7, 1.6), (0.2, 0.7), (1.6, 2.0)], 18)
    assert np.all((s >= 0.2) & (s <= 2.0)) and np.all(np.diff(s) > 0)
    np.testing.assert_allclose(s, 0.2 + (np.arange(18) + 0.5) * 0.1)
    split = sample_psi([(0.0, 1.0), (3.0, 4.0)], 4)
    np.testing.assert_allclose(split, [0.25, 0.75, 3.25, 3.75])
    np.testing.assert_array_equal(sample_psi([(0, 1)], 5, seed=3), sample_psi([(0, 1)], 5, seed=3))


def test_original_mode_has_zero_offsets(far):
    motion, task, table, _, _ = far
    data = build_tracking_data(motion, task, table, "original")
    assert data.num_samples == 1 and data.psi[0] == 1.1 and not data.keyframe_offsets.any()


def test_datasets_round_trip(far, tmp_path):
    _, _, _, edit, rule = far
    for data, name in ((edit, "d_edit"), (rule, "d_rule")):
        write_tracking_dataset(tmp_path / name, data)
        back = load_tracking_data(tmp_path / name)
        np.testing.assert_array_equal(back.psi, data.psi)
        np.testing.assert_array_equal(back.keyframe_offsets, data.keyframe_offsets)
        np.testing.assert_array_equal(back.keyframe_frames, data.keyframe_frames)
        np.testing.assert_array_equal(back.motion.joint_pos, data.motion.joint_pos)
        np.testing.assert_allclose(back.motion.body_pos, data.motion.body_pos, atol=1e-12)
        assert back.keyframe_labels == data.keyframe_labels and back.terrain == data.terrain
        assert back.psi_raw == data.psi_raw and back.psi_ranges["hard"] == [(0.2, 0.7), (1.6, 2.0)]
        if data.dense_offsets is None:
            assert back.dense_offsets is None
        else:
            np.testing.assert_array_equal(back.dense_offsets, data.dense_offsets)


def test_figure_and_video_written(far, tmp_path):
    import cv2

    from pipeline.keyframes.figure import keyframe_figure
    from pipeline.keyframes.rule_video import rule_video

    motion, task, table, edit, _ = far
    keyframe_figure(edit, tmp_path / "kf.png")
    assert (tmp_path / "kf.png").stat().st_size > 10_000
    short = motion.slice(0, 60)
    flat = TaskConfig.from_dict("s", {"input": "x.npz", "edit": "x", "psi": FAR,
                                      "keyframes": [{"time": 0.2}, {"time": 0.9, "label": "landing"}]})
    rule = build_tracking_data(short, flat, select_keyframes(short, flat), "rule", 3)
    rule_video(rule, tmp_path / "rule.mp4", fps_out=10)
    cap = cv2.VideoCapture(str(tmp_path / "rule.mp4"))
    ok, frame = cap.read()
    assert ok and frame.shape[2] == 3 and cap.get(cv2.CAP_PROP_FRAME_COUNT) >= 10


def test_tennis_psi_moves_the_hit_further_along_the_persons_shuffle():
    """The shared tennis clip, retargeted: ψ (the hit's lateral distance) moves the hit keyframe, and the ones after
    it, along the way the person shuffles, so a larger ψ reaches further from the start; nothing before the hit moves."""
    from pathlib import Path

    from pipeline.config import paper_tasks
    from pipeline.human.importers import load_human_motion
    from pipeline.keyframes.task_parsing import load_tasks
    from pipeline.retarget import RetargetConfig, retarget

    clip = Path(__file__).resolve().parents[2] / "shared" / "data" / "adamimic_smpl" / "tennis_hit.npz"
    if not clip.exists():
        pytest.skip(f"{clip} not present")
    task = load_tasks(paper_tasks())["tennis_hit"]
    motion, _ = retarget(load_human_motion(clip), RetargetConfig(), progress=False)
    table = select_keyframes(motion, task)
    data = build_tracking_data(motion, task, table, "edit", 4)
    hit = list(data.keyframe_labels).index("hit")
    start = motion.root_pos[0, :2]
    shuffle = motion.root_pos[table.frames[hit], :2] - start  # the unedited hit, from the start
    reach = (motion.root_pos[table.frames, :2][None] + data.keyframe_offsets[..., :2] - start) @ (shuffle / np.linalg.norm(shuffle))
    assert not data.keyframe_offsets[:, :hit].any()
    assert np.all(np.diff(reach[:, hit]) > 0) and np.all(np.diff(reach[:, -1]) > 0)  # ψ ascending: further
    np.testing.assert_allclose(np.diff(reach[:, hit]), np.diff(data.psi) * abs(shuffle[1]) / np.linalg.norm(shuffle),
                               rtol=1e-6)
