"""Preview video: the person (SMPL joints scaled to the robot's size) beside the retargeted G1.

Drawn through the project's renderer (pipeline/render: the styled scene, a camera following the pair, a
caption), the person as capsules 1 m to the robot's left, seen from three quarters so neither hides the
other. If no GL context can be made the frames are drawn with matplotlib (3D sticks) instead. H.264, written
atomically (pipeline/render/mp4.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.human.motion import SMPL_PARENTS, HumanMotion
from pipeline.motion.motion import Motion

SIDE_OFFSET = np.array([0.0, 1.0, 0.0])
PERSON_RGBA = np.array([0.95, 0.6, 0.2, 1.0], dtype=np.float32)


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
                  width: int = 960, height: int = 540, progress: bool = True, duration_scale: float = 1.0,
                  title: str = "", fps_out: float = 25.0) -> Path:
    """The preview in real time at about `fps_out` (every k-th frame of the motion)."""
    from tqdm import tqdm

    from pipeline.render.mp4 import Mp4Writer

    scale = scale if scale is not None else 1.32 / human.height
    skeleton = _human_at(human, motion, scale, duration_scale)
    step = max(1, int(round(motion.fps / fps_out)))
    shown = range(0, motion.num_frames, step)
    try:
        frames = _mujoco_frames(motion, skeleton, width, height, title, shown)
    except Exception:  # noqa: BLE001 - no GL context here: draw with matplotlib instead
        frames = _matplotlib_frames(motion, skeleton, width, height, shown)
    writer = Mp4Writer(path, max(1, int(round(motion.fps / step))), width, height)
    for rgb in tqdm(frames, total=len(shown), desc="preview", disable=not progress, leave=False):
        writer.add(rgb)
    return writer.close()


def _mujoco_frames(motion: Motion, skeleton: np.ndarray, width: int, height: int, title: str, shown: range):
    import mujoco

    from pipeline.render.renderer import CameraRig, Renderer
    from pipeline.robot.g1 import build_model, joint_qpos_indices

    model = build_model(visual=True)
    data = mujoco.MjData(model)
    renderer = Renderer(model, width, height, rig=CameraRig(distance=4.2, azimuth=125.0, elevation=-12.0, height=0.7))
    qidx = joint_qpos_indices(model, motion.joint_names)

    def frames():
        try:
            for t in shown:
                data.qpos[:3] = motion.root_pos[t]
                data.qpos[3:7] = motion.root_quat[t]
                data.qpos[qidx] = motion.joint_pos[t]
                mujoco.mj_kinematics(model, data)
                caption = [f"{title}   t {t / motion.fps:4.2f} s".strip(), "G1 (retargeted)  ·  person (scaled)"]
                yield renderer.frame(data, follow=motion.root_pos[t] + 0.5 * SIDE_OFFSET, caption=caption,
                                     decorate=lambda scene, t=t: _draw_skeleton(scene, skeleton[t]))
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
                            PERSON_RGBA)
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, 0.025, joints[parent], joints[child])
        scene.ngeom += 1


def _matplotlib_frames(motion: Motion, skeleton: np.ndarray, width: int, height: int, shown: range):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_subplot(projection="3d")

    def frames():
        try:
            for t in shown:
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
                rgb = np.asarray(fig.canvas.buffer_rgba())[:, :, :3]
                yield np.ascontiguousarray(rgb[:height, :width])
        finally:
            plt.close(fig)

    return frames()
