"""Terrain: builds and compiles for every paper task, one structure for every ψ, gaps and steps where
the edited reference takes off and lands, clear errors when it cannot be built."""

from pathlib import Path

import mujoco
import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.common.yaml_strict import load_yaml_strict
from pipeline.keyframes.config import TaskConfig
from pipeline.keyframes.task_parsing import load_tasks
from pipeline.keyframes.edit import build_tracking_data
from pipeline.keyframes.select import select_keyframes
from pipeline.motion.feet import foot_height_and_speed, sole_points_world
from pipeline.keyframes.synthetic import Flight, synthetic_jump_motion
from pipeline.keyframes.terrain import apply_layout, terrain_builder, terrain_layout
from pipeline.robot.g1 import build_spec

TASKS = load_tasks(load_yaml_strict(Path(__file__).resolve().parents[1] / "pipeline/keyframes/paper_tasks.yaml")["tasks"])
CLIPS = {  # synthetic stand-ins with the shape of each paper clip
    "far_jump": dict(flights=[Flight(1.0, 0.4, 1.1)]),
    "high_jump": dict(flights=[Flight(1.0, 0.5, 0.1)]),
    "triple_jump": dict(flights=[Flight(0.6, 0.3, 0.8), Flight(1.2, 0.3, 0.7), Flight(1.8, 0.4, 0.9)]),
    "jump_step_up": dict(flights=[Flight(1.0, 0.3, 0.5, 0.2)]),
    "jump_step_down": dict(flights=[Flight(1.0, 0.34, 0.4, -0.2)]),
    "tennis_hit": dict(flights=[], hit_time=1.5),
    "badminton_hit": dict(flights=[Flight(0.8, 0.3, 0.5)], hit_time=2.0, heading=0.4),
}


def _data(name, num=5):
    spec = CLIPS[name]
    motion = synthetic_jump_motion(spec["flights"], duration=3.0, hit_time=spec.get("hit_time"),
                                   heading=spec.get("heading", 0.0))
    task = TASKS[name]
    return motion, build_tracking_data(motion, task, select_keyframes(motion, task), "edit", num)


@pytest.mark.parametrize("name", sorted(CLIPS))
def test_terrain_builds_and_compiles_for_each_task(name):
    motion, data = _data(name)
    model = build_spec(terrain=terrain_builder(data), visual=False).compile()
    names = {model.geom(g).name for g in range(model.ngeom)}
    layouts = [terrain_layout(data, p) for p in data.psi]
    assert all(set(lay) == set(layouts[0]) for lay in layouts)  # one structure for every ψ
    assert set(layouts[0]) <= names
    if data.terrain["kind"] == "flat":
        assert "ground" in names and layouts[0] == {}
    mj = mujoco.MjData(model)
    for lay in layouts:
        apply_layout(model, lay)
        mujoco.mj_forward(model, mj)


def _top_under(model, data_mj, x: float, y: float) -> float | None:
    """Height of the highest terrain box top under the point (None over a gap)."""
    best = None
    for g in range(model.ngeom):
        if not model.geom(g).name.startswith("terrain_box"):
            continue
        local = data_mj.geom_xmat[g].reshape(3, 3).T @ (np.array([x, y, 0.0]) - data_mj.geom_xpos[g])
        size = model.geom_size[g]
        if abs(local[0]) <= size[0] and abs(local[1]) <= size[1]:
            top = data_mj.geom_xpos[g][2] + size[2]
            best = top if best is None else max(best, top)
    return best


@pytest.mark.parametrize("name", ["far_jump", "triple_jump", "jump_step_up", "jump_step_down"])
def test_edited_reference_lands_on_the_terrain(name):
    motion, data = _data(name, num=7)
    model = build_spec(terrain=terrain_builder(data), visual=False).compile()
    mj = mujoco.MjData(model)
    soles = sole_points_world(motion)
    heights, _ = foot_height_and_speed(motion)
    landings = [k for k, lab in enumerate(data.keyframe_labels) if lab.startswith("landing")]
    takeoffs = [k for k, lab in enumerate(data.keyframe_labels) if lab.startswith("takeoff")]
    for n, psi in enumerate(data.psi):
        apply_layout(model, terrain_layout(data, psi))
        mujoco.mj_kinematics(model, mj)
        for k in landings + takeoffs:
            frame = data.keyframe_frames[k]
            off = data.keyframe_offsets[n, k]
            lowest = np.unravel_index(np.argmin(soles[frame, ..., 2]), soles.shape[1:3])
            foot = soles[frame][lowest] + off
            top = _top_under(model, mj, foot[0], foot[1])
            assert top is not None, f"{name} ψ={psi:.2f}: foot over a gap at keyframe {data.keyframe_labels[k]}"
            # the sole (capsule surface) sits on the box top
            assert abs(heights[frame].min() + off[2] - top) < 0.02
        if name in ("far_jump", "triple_jump") and psi > data.psi_raw:
            # a real gap lies between takeoff and landing of the first jump
            a = soles[data.keyframe_frames[takeoffs[0]]].reshape(-1, 3)[:, 0].max() + data.keyframe_offsets[n, takeoffs[0], 0]
            b = soles[data.keyframe_frames[landings[0]]].reshape(-1, 3)[:, 0].min() + data.keyframe_offsets[n, landings[0], 0]
            assert _top_under(model, mj, 0.5 * (a + b), 0.0) is None


def test_step_height_follows_psi():
    _, data = _data("jump_step_up", num=3)
    tops = [terrain_layout(data, p)["terrain_box_1"][0][2] for p in (0.1, 0.3, 0.5)]
    np.testing.assert_allclose(np.diff(tops), [0.2, 0.2], atol=1e-12)
    _, down = _data("jump_step_down", num=3)
    tops = [terrain_layout(down, p)["terrain_box_1"][0][2] for p in (0.1, 0.3)]
    assert tops[1] < tops[0]


def test_unbuildable_terrain_is_a_clear_error():
    motion = synthetic_jump_motion([Flight(1.0, 0.4, 1.1)], duration=3.0)
    no_takeoff = TaskConfig.from_dict("g", {"input": "x.npz", "edit": "x", "terrain": "gap",
                                            "psi": {"raw": 1.1, "easy": [[0.7, 1.6]]},
                                            "keyframes": [{"time": 0.5}, {"time": 1.4, "label": "landing"}]})
    with pytest.raises(PipelineInputError) as err:
        build_tracking_data(motion, no_takeoff, select_keyframes(motion, no_takeoff), "edit", 3)
    assert err.value.source == "task g" and err.value.field == "terrain" and "takeoff" in err.value.problem
    with pytest.raises(PipelineInputError, match="anchors"):
        terrain_layout(TASKS["far_jump"], 1.0)  # not resolved on a motion yet
    with pytest.raises(PipelineInputError, match="too high|exceed"):
        _, data = _data("jump_step_up", num=2)
        terrain_layout(data, 3.0)
