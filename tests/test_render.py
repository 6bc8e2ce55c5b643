"""The project's renderer (pipeline/render): the ghost and the obstacle are drawn, the caption prints, the
reference pose an export carries, and a chain's video spans the whole chain."""

import json

import mujoco
import numpy as np
import pytest

from pipeline.render.caption import draw_caption
from pipeline.render.renderer import CameraRig, Renderer
from pipeline.render.style import OBSTACLE_MATERIAL, mark_raised_terrain
from pipeline.robot.g1 import build_model, build_spec, default_qpos

W, H = 160, 96


def _standing(model):
    data = mujoco.MjData(model)
    data.qpos[:] = default_qpos()
    mujoco.mj_kinematics(model, data)
    return data


def _blue(frame):
    """Pixels clearly bluer than they are red: the ghost's colour; the grey robot, floor and sky are not."""
    rgb = frame.astype(int)
    return (rgb[..., 2] - rgb[..., 0] > 60) & (rgb[..., 2] > 120) & (rgb[..., 1] < rgb[..., 2] - 20)


def _orange(frame):
    rgb = frame.astype(int)
    return (rgb[..., 0] - rgb[..., 2] > 80) & (rgb[..., 0] > 120)


def test_the_ghost_is_drawn_where_the_reference_is_and_leaves_the_scene_alone():
    model = build_model(visual=True)
    data = _standing(model)
    renderer = Renderer(model, W, H, rig=CameraRig(distance=3.0))
    try:
        plain = renderer.frame(data)
        ghost_qpos = data.qpos.copy()
        ghost_qpos[0] += 0.8  # a metre to the right on screen: the side camera looks along +y
        with_ghost = renderer.frame(data, ghosts=[(ghost_qpos, None)])
    finally:
        renderer.close()
    assert _blue(plain).sum() == 0
    blue = _blue(with_ghost)
    assert blue.sum() > 50
    columns = np.nonzero(blue.any(axis=0))[0]
    assert columns.min() > W // 2  # right of the robot, which the camera centres
    assert np.array_equal(data.qpos[:7], default_qpos()[:7])  # the drawn scene's state is untouched


def test_the_obstacle_stands_out_a_step_raised_side_and_a_gap_pit():
    from pipeline.keyframes.terrain import apply_layout, terrain_builder, terrain_layout

    step = {"kind": "step", "margin": 0.1, "anchors": {"direction": [1.0, 0.0], "psi_raw": 0.0, "sign": -1.0,
                                                       "start_floor": 0.0, "steps": [{"edge": 0.4, "floor": 0.0,
                                                                                      "share": 1.0}]}}
    model = build_spec(terrain=terrain_builder(step), visual=True).compile()
    apply_layout(model, terrain_layout(step, 0.3))  # the start 0.3 m above the landing
    assert mark_raised_terrain(model) == 1
    material = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, OBSTACLE_MATERIAL)
    raised = [i for i in range(model.ngeom) if model.geom_matid[i] == material]
    assert len(raised) == 1 and model.geom_pos[raised[0], 0] < 0.4  # the ledge the robot steps off
    renderer = Renderer(model, W, H, rig=CameraRig(distance=2.5, elevation=-30.0))
    try:
        frame = renderer.frame(_standing(model))
    finally:
        renderer.close()
    assert _orange(frame).sum() > 200


def test_the_caption_prints_greek_letters_on_a_dark_box():
    frame = np.full((H, W, 3), 230, np.uint8)
    out = draw_caption(frame, ["far_jump   ψ 1.30 m", "task policy  φ 0.42"])
    assert out.shape == frame.shape and out.dtype == np.uint8
    corner, elsewhere = out[: H // 3, : W // 2], out[H // 2:, W // 2:]
    assert corner.mean() < 200 and (corner > 240).any()  # dark box, white letters
    assert np.array_equal(elsewhere, frame[H // 2:, W // 2:])


@pytest.fixture(scope="module")
def chain_export(tmp_path_factory):
    from test_chain import chained_export, standin_task_export

    root = tmp_path_factory.mktemp("render")
    return chained_export(standin_task_export(root / "task"), root / "export", stand_s=0.4, after_s=0.4)


def test_an_export_carries_the_reference_pose_the_ghost_follows(chain_export):
    from pipeline.render.reference import ReferencePose

    meta = json.loads((chain_export / "policy.json").read_text())
    reference = ReferencePose.from_metadata(meta)
    assert reference is not None and reference.num_frames == meta["reference"]["num_frames"]
    model = build_model(visual=True)
    psi = max(meta["psi_ranges"]["easy"][0])
    start, end = reference.qpos(model, psi, 0.0), reference.qpos(model, psi, 1.0)
    targets = np.asarray(meta["keyframes"]["body_pos"])  # (K, B, 3) unedited
    # the ghost ends moved by the last keyframe's edit at this ψ, and starts unmoved by it
    from pipeline.export.sim2sim import _interp_grid

    edit = _interp_grid(meta["keyframes"]["psi_grid"], np.asarray(meta["keyframes"]["offsets"]), psi)
    assert np.allclose(end[:3] - np.asarray(meta["reference"]["root_pos"][-1]), edit[-1], atol=1e-9)
    assert np.allclose(start[:3] - np.asarray(meta["reference"]["root_pos"][0]), edit[0], atol=1e-9)
    assert targets.shape[0] == edit.shape[0]
    del meta["reference"]["root_pos"]  # an export made before the pose was stored: no ghost, no error
    assert ReferencePose.from_metadata(meta) is None


def test_a_chain_video_spans_the_whole_chain(chain_export, tmp_path):
    import av

    from pipeline.export.chain import ChainRunner
    from pipeline.export.play import play_to_mp4

    result = ChainRunner(chain_export).run(1.3)
    control_steps = sum(result.steps.values())
    out = play_to_mp4(chain_export, 1.3, tmp_path / "chain.mp4", width=W, height=H, fps=25)
    with av.open(str(out)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == control_steps // 2  # every other 50 Hz step: 25 fps, real time
    assert result.steps["stand"] > 0 and result.steps["task"] > 0
    assert frames[0].shape == (H, W, 3) and _blue(frames[len(frames) // 2]).sum() > 0  # the ghost is there
