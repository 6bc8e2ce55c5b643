"""Automatic keyframes: takeoff/landing/apex/hit on synthetic jumps with known contacts and on the
real shared far jump (retargeted), against MuJoCo's own foot geometry."""

from pathlib import Path

import mujoco
import numpy as np
import pytest

from pipeline.keyframes.config import TaskConfig
from pipeline.keyframes.select import find_flights, select_keyframes
from pipeline.motion.feet import detect_foot_contacts
from pipeline.keyframes.synthetic import Flight, synthetic_jump_motion, true_flight_frames

FAR_JUMP = Path(__file__).resolve().parents[2] / "shared/data/adamimic_smpl/far_jump.npz"
PSI = {"raw": 1.1, "easy": [[0.7, 1.6]], "hard": [[0.2, 0.7], [1.6, 2.0]]}


def _task(**changes):
    return TaskConfig.from_dict("t", {"input": "x.npz", "edit": "x", "psi": PSI, **changes})


@pytest.mark.parametrize("flights", [
    [Flight(1.0, 0.4, 1.1)],                                               # far jump
    [Flight(1.0, 0.3, 0.5, 0.2)],                                          # onto a step
    [Flight(1.0, 0.34, 0.4, -0.25)],                                       # down a step
    [Flight(0.6, 0.3, 0.8), Flight(1.2, 0.3, 0.7), Flight(1.8, 0.4, 0.9)],  # triple jump
])
def test_takeoff_landing_within_two_frames_of_contacts(flights):
    motion = synthetic_jump_motion(flights, duration=3.0)
    found = find_flights(detect_foot_contacts(motion), motion.fps, 0.08)
    truth = true_flight_frames(flights, motion.fps)
    assert len(found) == len(truth)
    for (a, b), (ta, tb) in zip(found, truth):
        assert abs(a - ta) <= 2 and abs(b - tb) <= 2


def test_apex_and_hit_found():
    motion = synthetic_jump_motion([Flight(1.0, 0.5, 0.1)], duration=3.0, hit_time=2.4)
    task = _task(edit={"mode": "z_apex"}, keyframes={"events": ["takeoff", "apex", "landing", "hit"]},
                 psi={"raw": 0.2, "easy": [[0.1, 0.35]]})
    table = select_keyframes(motion, task)
    labels = list(table.labels)
    apex = table.frames[labels.index("apex")]
    assert abs(apex - np.argmax(motion.root_pos[:, 2])) <= 1
    assert abs(table.frames[labels.index("hit")] - round(2.4 * motion.fps)) <= 2
    assert table.edited[labels.index("apex")] and table.edited.sum() == 1


def test_table_uniform_fill_scale_and_overrides():
    motion = synthetic_jump_motion([Flight(1.0, 0.4, 1.1)], duration=3.0)
    table = select_keyframes(motion, _task())
    takeoff, landing = table.frames[list(table.labels).index("takeoff")], table.frames[list(table.labels).index("landing")]
    assert np.all(np.diff(table.frames) > 0)
    assert not np.any((table.frames > takeoff) & (table.frames < landing))  # nothing in mid-air
    gaps = np.diff(table.times)
    assert gaps.max() <= 0.3 + 0.12 + 1e-9 and table.times[0] == pytest.approx(0.1)
    np.testing.assert_array_equal(table.sparse_scale, np.where([bool(l) for l in table.labels], 50.0, 1.0))
    assert table.edited.tolist() == [l == "landing" for l in table.labels]

    over = select_keyframes(motion, _task(keyframes={"overrides": {"landing": 1.5}, "extra": [{"time": 1.2, "label": "apex"}]},
                                          sparse_scale={"large": 20, "keyframes": ["landing"]}))
    labels = list(over.labels)
    assert over.times[labels.index("landing")] == pytest.approx(1.5)
    assert over.times[labels.index("apex")] == pytest.approx(1.2)
    assert over.sparse_scale[labels.index("landing")] == 20 and over.sparse_scale[labels.index("takeoff")] == 1

    explicit = select_keyframes(motion, _task(keyframes=[{"time": 0.2}, {"time": 1.4, "label": "landing"}, {"time": 2.0}]))
    assert explicit.frames.tolist() == [10, 70, 100] and explicit.edited.tolist() == [False, True, False]


def _mujoco_foot_heights(motion) -> np.ndarray:
    """(T, 2) lowest point of each foot's collision capsules, straight from MuJoCo's kinematics."""
    from pipeline.robot.g1 import build_model

    model = build_model(visual=False)
    data = mujoco.MjData(model)
    feet = [[g for g in range(model.ngeom) if model.geom(g).name.startswith(f"{s}_foot")] for s in ("left", "right")]
    qpos = motion.qpos()
    out = np.zeros((motion.num_frames, 2))
    for t in range(motion.num_frames):
        data.qpos[:] = qpos[t]
        mujoco.mj_kinematics(model, data)
        for i, geoms in enumerate(feet):
            z = [data.geom_xpos[g][2] + s * data.geom_xmat[g][8] * model.geom_size[g][1] - model.geom_size[g][0]
                 for g in geoms for s in (-1, 1)]
            out[t, i] = min(z)
    return out


@pytest.mark.skipif(not FAR_JUMP.exists(), reason="shared far jump not present")
def test_real_far_jump_takeoff_landing_match_contacts():
    from pipeline.human.importers import load_human_motion
    from pipeline.retarget.core import retarget

    motion, report = retarget(load_human_motion(FAR_JUMP), progress=False)
    table = select_keyframes(motion, _task())
    labels = list(table.labels)
    takeoff, landing = table.frames[labels.index("takeoff")], table.frames[labels.index("landing")]
    # Contacts as physics sees them: a foot capsule within 5 mm of the floor.
    contact = (_mujoco_foot_heights(motion) < 0.005).any(axis=1)
    airborne = np.flatnonzero(~contact)
    longest = max(np.split(airborne, np.flatnonzero(np.diff(airborne) > 1) + 1), key=len)
    assert abs(takeoff - (longest[0] - 1)) <= 2
    assert abs(landing - (longest[-1] + 1)) <= 2
    # The flight found is a forward one (the retargeted feet slide on late, so the root covers
    # less than the human's 1.1 m while both feet are off the floor).
    assert motion.root_pos[landing, 0] - motion.root_pos[takeoff, 0] > 0.3
    assert len(table.flights) == 1
