"""Flights and foot contacts (`motion/feet.py`, the one detector of both) on references that look like a
pose estimator's: a hop, step and jump with jittery feet, sliding stances and a sloped floor; what the
keyframes, the terrain and quality.json make of them; a declared number of flights; flights by hand;
and the shared real clips, which must keep the flights they have always had."""

from pathlib import Path

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.keyframes.config import TaskConfig
from pipeline.keyframes.select import select_keyframes
from pipeline.keyframes.synthetic import (CLEAN, EstimatorNoise, Flight, hop_step_jump_supports,
                                          synthetic_hop_step_jump, synthetic_jump_motion)
from pipeline.motion.feet import detect_foot_contacts, find_flights, height_jitter, foot_height_and_speed

SHARED = Path(__file__).resolve().parents[2] / "shared/data/adamimic_smpl"
TRIPLE = {"input": "clips/triple.npz", "edit": {"mode": "x", "keyframes": ["landing"]},
          "psi": {"raw": 2.4, "easy": [[1.65, 3.15]]}, "terrain": "gap"}


def _frame_errors(found, truth) -> np.ndarray:
    return np.abs(np.array(found) - np.array(truth)).ravel()


@pytest.fixture(scope="module")
def noisy_clips():
    """Six hop-step-jumps, each with its own jitter, on floors rising and falling 4 % and 5 %."""
    return [synthetic_hop_step_jump(noise=EstimatorNoise(seed=seed, slope=(0.04, -0.05)[seed % 2]))
            for seed in range(6)]


def test_clean_hop_step_jump_flights_exact():
    """Without an estimator's noise: the three flights to the frame; the walking steps before them,
    whose contacts abut (one foot lands on the frame the other leaves), are none."""
    motion, contacts, truth = synthetic_hop_step_jump(noise=CLEAN)
    assert len(truth) == 3 and height_jitter(foot_height_and_speed(motion)[0], motion.fps) < 1e-4
    found = find_flights(detect_foot_contacts(motion), motion.fps)
    assert found == truth
    # Each foot's contact to the frame, heel strikes and toe-offs included.
    np.testing.assert_array_equal(detect_foot_contacts(motion), contacts)


def test_jittery_hop_step_jump_finds_three_flights(noisy_clips):
    """GVHMR-like: feet jittering by a centimetre at 30 fps, standing feet creeping at 0.15 m/s, a
    sloped floor. Every clip has exactly the three flights (0.16, 0.2 and 0.24 s long), their take-offs
    and landings within a frame or two nine times in ten, never more than three off (the tolerances a
    centimetre of jitter needs cost a foot coming down or going up slowly a frame or so;
    benchmarks/flight_detection.py measures more clips)."""
    errors = []
    for motion, _, truth in noisy_clips:
        assert height_jitter(foot_height_and_speed(motion)[0], motion.fps) > 0.002  # read as a jittery clip
        found = find_flights(detect_foot_contacts(motion), motion.fps)
        assert len(found) == 3, (found, truth)
        errors.append(_frame_errors(found, truth))
    errors = np.concatenate(errors)
    assert errors.max() <= 3, errors
    assert np.mean(errors <= 2) >= 0.9 and np.mean(errors <= 1) >= 0.8, errors


def test_jittery_short_flights_and_short_stances():
    """Flights of 0.1, 0.12 and 0.16 s between stances of 0.16 s, downhill, eight jitters: the three
    flights in at least seven (a 0.1 s flight is 4 frames in the air, and a centimetre of jitter may take
    a frame or two of it)."""
    supports = hop_step_jump_supports(flights=(0.1, 0.12, 0.16), stance=0.16)
    right = 0
    for seed in range(8):
        motion, _, truth = synthetic_hop_step_jump(supports, EstimatorNoise(seed=10 + seed, slope=-0.05))
        found = find_flights(detect_foot_contacts(motion), motion.fps)
        if len(found) == 3:
            right += 1
            assert _frame_errors(found, truth).max() <= 3, (seed, found, truth)
    assert right >= 7


def test_jittery_vertical_jump_has_no_floor_in_the_air():
    """Feet still at the top of a high jump are not standing on anything, jitter or not."""
    clean = synthetic_jump_motion([Flight(1.0, 0.6, 0.1)], duration=3.0)
    rng = np.random.default_rng(0)
    from pipeline.motion.motion import RobotKinematics

    root = clean.root_pos + rng.normal(0.0, 0.006, clean.root_pos.shape)
    motion = RobotKinematics().motion(clean.fps, root, clean.root_quat, clean.joint_pos)
    found = find_flights(detect_foot_contacts(motion), motion.fps)
    assert len(found) == 1
    assert _frame_errors(found, [(50, 80)]).max() <= 2


# ------------------------------------------------------------------------------ tasks
def test_triple_jump_keyframes_and_terrain(noisy_clips):
    """The paper's triple jump on a jittery hop-step-jump: numbered takeoffs and landings, all three
    landings edited, and three gaps, each from the take-off foot's toes forward to the landing foot's
    heels (a hop's swinging foot is ahead of the take-off: it must not drag the edge back), one after
    the other."""
    from pipeline.config import paper_tasks
    from pipeline.keyframes.edit import build_tracking_data

    motion, _, truth = noisy_clips[0]
    task = TaskConfig.from_dict("triple_jump", {**paper_tasks()["triple_jump"], "input": "x.npz", "num_samples": 4})
    assert task.keyframes.flight_count == 3
    table = select_keyframes(motion, task)
    assert len(table.flights) == 3
    labels = [label for label in table.labels if label]
    assert labels == ["takeoff_1", "landing_1", "takeoff_2", "landing_2", "takeoff_3", "landing_3"]
    assert [label for label, e in zip(table.labels, table.edited) if e] == ["landing_1", "landing_2", "landing_3"]
    gaps = build_tracking_data(motion, task, table, "edit", 4, 0).terrain["anchors"]["gaps"]
    assert len(gaps) == 3
    edges = [edge for g in gaps for edge in (g["takeoff"], g["landing"])]
    assert all(b > a for a, b in zip(edges, edges[1:])), edges


def test_declared_flight_count_mismatch_names_clip_frames_and_the_fix(noisy_clips):
    motion = noisy_clips[1][0]
    task = TaskConfig.from_dict("tj", {**TRIPLE, "keyframes": {"flights": 2}})
    with pytest.raises(PipelineInputError) as err:
        select_keyframes(motion, task)
    message = str(err.value)
    assert "clips/triple.npz" in message and "keyframes.flights" in message
    assert "2 flight(s) but 3 were found" in message
    found = find_flights(detect_foot_contacts(motion), motion.fps)
    assert f"frames {found[0][0]}-{found[0][1]}" in message
    assert "keyframes: {flights: [[" in message  # how to list them by hand


def test_flights_listed_by_hand(noisy_clips):
    """`keyframes.flights` as [take-off, landing] times: exactly those, nothing detected."""
    motion = noisy_clips[2][0]
    listed = [[2.3, 2.46], [2.66, 2.86], [3.06, 3.3]]
    table = select_keyframes(motion, TaskConfig.from_dict("tj", {**TRIPLE, "keyframes": {"flights": listed}}))
    assert [list(f) for f in table.flights] == [[115, 123], [133, 143], [153, 165]]
    frames = dict(zip(table.labels, table.frames))
    assert (frames["takeoff_2"], frames["landing_2"]) == (133, 143)
    with pytest.raises(PipelineInputError, match=r"keyframes.flights\[0\].*beyond the end"):
        select_keyframes(motion, TaskConfig.from_dict("tj", {**TRIPLE, "keyframes": {"flights": [[3.0, 9.0]]}}))


@pytest.mark.parametrize("flights, field, problem", [
    (-1, "keyframes.flights", ">= 0"),
    ("three", "keyframes.flights", "number of flights"),
    ([], "keyframes.flights", "number of flights"),
    ([[1.0]], r"keyframes.flights\[0\]", r"\[take-off, landing\]"),
    ([[1.0, 0.8]], r"keyframes.flights\[0\]", "after the take-off"),
    ([[0.5, 1.0], [0.9, 1.2]], r"keyframes.flights\[1\]", "before the flight before it has landed"),
    ([[0.5, "1.0"]], r"keyframes.flights\[0\]", "finite number"),
])
def test_flights_key_validated(flights, field, problem):
    with pytest.raises(PipelineInputError, match=f"{field}.*{problem}"):
        TaskConfig.from_dict("tj", {**TRIPLE, "keyframes": {"flights": flights}})


def test_backward_gap_is_an_error_not_a_terrain():
    """A jump that lands behind its take-off would make a gap with its landing edge behind its take-off
    edge: the keyframes stage refuses it, naming the clip and the keyframes; declared anchors too."""
    from pipeline.keyframes.edit import build_tracking_data
    from pipeline.keyframes.terrain import terrain_layout

    motion = synthetic_jump_motion([Flight(1.0, 0.4, -0.6)], duration=3.0)
    task = TaskConfig.from_dict("back", {**TRIPLE, "input": "clips/back.npz", "psi": {"raw": 1.0, "easy": [[0.8, 1.2]]}})
    table = select_keyframes(motion, task)
    with pytest.raises(PipelineInputError, match=r"clips/back.npz: the gap before landing would run backwards"):
        build_tracking_data(motion, task, table, "edit", 4, 0)
    declared = {"kind": "gap", "anchors": {"psi_raw": 1.0, "gaps": [{"takeoff": 3.06, "landing": 2.57}]}}
    with pytest.raises(PipelineInputError, match=r"terrain.anchors.gaps\[0\].*behind the take-off edge"):
        terrain_layout(declared, 1.0)


def test_overlapping_gaps_refused_at_the_end_of_the_psi_range():
    """Two gaps whose ground between them vanishes at a ψ of the training range."""
    from pipeline.keyframes.terrain import terrain_layout

    terrain = {"kind": "gap", "anchors": {"psi_raw": 1.0, "gaps": [
        {"takeoff": 0.0, "landing": 1.0, "takeoff_share": 0.0, "landing_share": 1.0},
        {"takeoff": 1.6, "landing": 2.5, "takeoff_share": 0.0, "landing_share": 1.0}]}}
    terrain_layout(terrain, 1.0)
    with pytest.raises(PipelineInputError, match="gaps overlap"):
        terrain_layout(terrain, 2.0)


# ------------------------------------------------------------------------------ quality.json
def test_quality_jump_reports_every_flight(noisy_clips):
    from pipeline.retarget.quality import jump_summary

    motion, _, truth = noisy_clips[3]
    contacts = detect_foot_contacts(motion)
    com = motion.root_pos.copy()
    report = jump_summary(motion.root_pos, contacts, motion.fps, com=com)
    assert report["flights_found"] == 3 and len(report["flights"]) == 3
    durations = [f["duration_s"] for f in report["flights"]]
    np.testing.assert_allclose(durations, [0.16, 0.2, 0.24], atol=0.08)
    assert report["duration_s"] == max(durations)  # the longest one's figures at the top level
    for flight, (takeoff, landing) in zip(report["flights"], truth):
        assert abs(flight["takeoff_s"] - takeoff / motion.fps) <= 3 / motion.fps + 1e-9
        assert flight["distance_m"] > 0.2 and flight["gravity_m_s2"] is not None
    # A flight and the stance after it are never read as one: no flight lasts longer than the longest.
    assert report["duration_s"] < 0.3


# ------------------------------------------------------------------------------ real clips
@pytest.mark.parametrize("clip, flights", [
    ("far_jump", [(158, 174)]), ("high_jump", [(158, 187)]), ("jump_step_up", [(114, 139)]),
    ("jump_step_down", [(100, 122)]), ("tennis_hit", []),
])
def test_shared_clips_keep_their_flights(clip, flights):
    """The five shared real clips, retargeted: the flights (50 fps frames) the keyframes have always had."""
    path = SHARED / f"{clip}.npz"
    if not path.exists():
        pytest.skip(f"{path} not present")
    from pipeline.human.importers import load_human_motion
    from pipeline.retarget import RetargetConfig, retarget

    motion, report = retarget(load_human_motion(path), RetargetConfig(), progress=False)
    assert find_flights(detect_foot_contacts(motion), motion.fps) == flights
    assert report["jump"]["flights_found"] == len(flights)
    assert [(round(f["takeoff_s"] * 50), round(f["landing_s"] * 50)) for f in report["jump"]["flights"]] == flights
