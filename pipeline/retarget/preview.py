"""Preview video: the human skeleton (scaled to robot size) beside the retargeted G1.

MuJoCo offscreen rendering (MUJOCO_GL=egl works on this machine; osmesa does not), the skeleton
drawn as capsules into the same scene, 1 m to the robot's left. If no GL context can be made the
frames are drawn with matplotlib (3D sticks) instead. OpenCV writes mp4v; the file appears
atomically (temporary sibling, renamed into place).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.human.motion import SMPL_PARENTS, HumanMotion
from pipeline.motion.motion import Motion

SIDE_OFFSET = np.array([0.0, 1.0, 0.0])


def _human_at(human: HumanMotion, motion: Motion, scale: float, duration_scale: float = 1.0) -> np.ndarray:
    """(T_out, 22, 3) scaled human joints at the motion's frame times, beside the robot (the robot's
    clock runs `duration_scale` times the human's: retarget's `time_scale`)."""
    t = np.arange(motion.num_frames) / motion.fps / duration_scale * human.fps
    i0 = np.clip(np.floor(t).astype(int), 0, human.num_frames - 1)
    i1 = np.clip(i0 + 1, 0, human.num_frames - 1)
    a = (t - i0)[:, None, None]
    joints = human.joint_pos[i0] * (1 - a) + human.joint_pos[i1] * a
    return scale * joints + SIDE_OFFSET


def write_preview(human: HumanMotion, motion: Motion, path: str | Path, scale: float | None = None,
                  width: int = 640, height: int = 360, progress: bool = True, duration_scale: float = 1.0) -> Path:
    import cv2
    from tqdm import tqdm

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scale = scale if scale is not None else 1.32 / human.height
    skeleton = _human_at(human, motion, scale, duration_scale)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.mp4")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), motion.fps, (width, height))
    try:
        frames = _mujoco_frames(motion, skeleton, width, height)
    except Exception:  # noqa: BLE001 - no GL context here: draw with matplotlib instead
        frames = _matplotlib_frames(motion, skeleton, width, height)
    try:
        for rgb in tqdm(frames, total=motion.num_frames, desc="preview", disable=not progress, leave=False):
            writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        writer.release()
        os.replace(tmp, path)
    finally:
        writer.release()
        if tmp.exists():
            tmp.unlink()
    return path


def _mujoco_frames(motion: Motion, skeleton: np.ndarray, width: int, height: int):
    import mujoco

    from pipeline.robot.g1 import build_model, joint_qpos_indices

    model = build_model(visual=True)
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, height, width)  # fails here without a GL context
    qidx = joint_qpos_indices(model, motion.joint_names)
    camera = mujoco.MjvCamera()
    camera.distance, camera.elevation, camera.azimuth = 4.0, -15.0, 180.0 + 20.0

    def frames():
        try:
            for t in range(motion.num_frames):
                data.qpos[:3] = motion.root_pos[t]
                data.qpos[3:7] = motion.root_quat[t]
                data.qpos[qidx] = motion.joint_pos[t]
                mujoco.mj_forward(model, data)
                camera.lookat[:] = motion.root_pos[t] + 0.5 * SIDE_OFFSET
                camera.lookat[2] = 0.7
                renderer.update_scene(data, camera)
                _draw_skeleton(renderer.scene, skeleton[t])
                yield renderer.render()
        finally:
            renderer.close()

    return frames()


def _draw_skeleton(scene, joints: np.ndarray) -> None:
    import mujoco

    for child, parent in enumerate(SMPL_PARENTS):
        if parent < 0 or scene.ngeom >= scene.maxgeom:
            continue
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.eye(3).ravel(),
                            np.array([0.95, 0.6, 0.2, 1.0], dtype=np.float32))
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, 0.02, joints[parent], joints[child])
        scene.ngeom += 1


def _matplotlib_frames(motion: Motion, skeleton: np.ndarray, width: int, height: int):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_subplot(projection="3d")

    def frames():
        try:
            for t in range(motion.num_frames):
                ax.cla()
                for child, parent in enumerate(SMPL_PARENTS):
                    if parent >= 0:
                        seg = skeleton[t, [parent, child]]
                        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], color="tab:orange")
                body = motion.body_pos[t]
                ax.scatter(body[:, 0], body[:, 1], body[:, 2], color="tab:blue", s=8)
                c = motion.root_pos[t]
                ax.set_xlim(c[0] - 1, c[0] + 1)
                ax.set_ylim(c[1] - 0.5, c[1] + 1.5)
                ax.set_zlim(0, 2)
                fig.canvas.draw()
                yield np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy()
        finally:
            plt.close(fig)

    return frames()
