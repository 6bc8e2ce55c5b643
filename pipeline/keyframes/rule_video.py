"""The D_rule video: the retargeted reference (solid) and its dense edits for a few ψ as coloured ghosts of the
G1 (dark to light: smallest to largest ψ), each in its own lane beside the reference, drawn through the
project's renderer (pipeline/render) from three quarters; a caption names the task, the time and the ψ values.
A ghost's height is shown from its lowest point (a step down's edit lowers the landing: its ghost starts
raised and lands on the floor instead of sinking through it). Without GL the skeletons are drawn with
matplotlib instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.keyframes.tracking_data import TrackingData


LANE_M = 0.7  # lateral spacing of the ghosts


def _chosen(data: TrackingData, num_motions: int) -> np.ndarray:
    order = np.argsort(data.psi)
    return order[np.unique(np.linspace(0, len(order) - 1, min(num_motions, len(order))).round().astype(int))]


def rule_video(data: TrackingData, path: str | Path, num_motions: int = 5, fps_out: float = 25.0,
               size: tuple[int, int] = (960, 540)) -> Path:
    """An mp4 of D_rule motions (dense offsets) for a few ψ, written atomically."""
    if data.dense_offsets is None:
        raise ValueError("rule_video needs D_rule (TrackingData with dense_offsets)")
    try:
        frames = _ghost_frames(data, num_motions, fps_out, size)
    except RuntimeError:  # no GL context here
        _matplotlib_rule_video(data, path, num_motions, fps_out, size)
        return Path(path)
    from pipeline.render.mp4 import Mp4Writer

    step = max(1, int(round(data.motion.fps / fps_out)))
    writer = Mp4Writer(path, int(round(data.motion.fps / step)), *size)
    for frame in frames:
        writer.add(frame)
    return writer.close()


def _ghost_frames(data: TrackingData, num_motions: int, fps_out: float, size: tuple[int, int]):
    import matplotlib
    import mujoco

    from pipeline.render.renderer import CameraRig, Renderer
    from pipeline.robot.g1 import build_model, joint_qpos_indices

    motion = data.motion
    model = build_model(visual=True)
    chosen = _chosen(data, num_motions)
    lanes = LANE_M * np.arange(1, len(chosen) + 1)
    rig = CameraRig(distance=3.0 + 0.5 * lanes[-1], azimuth=135.0, elevation=-15.0)
    # no shadow: five ghosts' meshes through a shadow pass would cost three times as much on a CPU
    renderer = Renderer(model, *size, rig=rig, shadows=False)  # raises RuntimeError without GL, before any frame
    scene_data = mujoco.MjData(model)
    qidx = joint_qpos_indices(model, motion.joint_names)
    offsets = data.dense_offsets[chosen].copy()  # (N, T, 3)
    offsets[..., 2] -= np.minimum(offsets[..., 2].min(axis=1, keepdims=True), 0.0)
    offsets[..., 1] += lanes[:, None]
    colors = matplotlib.colormaps["viridis"](np.linspace(0.1, 0.9, len(chosen)))
    colors[:, 3] = 0.4
    step = max(1, int(round(motion.fps / fps_out)))
    psi_text = ", ".join(f"{data.psi[n]:.2f}" for n in chosen)

    def pose(t: int, offset) -> np.ndarray:
        qpos = np.zeros(model.nq)
        qpos[0:3], qpos[3:7], qpos[qidx] = motion.root_pos[t] + offset, motion.root_quat[t], motion.joint_pos[t]
        return qpos

    def frames():
        try:
            for t in range(0, motion.num_frames, step):
                scene_data.qpos[:] = pose(t, 0.0)
                mujoco.mj_kinematics(model, scene_data)
                ghosts = [(pose(t, offsets[i, t]), color) for i, color in enumerate(colors)]
                follow = motion.root_pos[t] + 0.5 * (offsets[:, t].mean(axis=0) * [1, 1, 0])
                yield renderer.frame(scene_data, follow=follow, ghosts=ghosts, caption=[
                    f"{data.task}  D_rule   t {t / motion.fps:4.2f} s",
                    f"solid: the reference;  beside it, ψ {psi_text} m (dark → light)"])
        finally:
            renderer.close()

    return frames()


def _matplotlib_rule_video(data: TrackingData, path: str | Path, num_motions: int = 5, fps_out: float = 25.0,
               size: tuple[int, int] = (640, 360)) -> None:
    """The fallback without GL: skeletons in a side view drawn with matplotlib."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.keyframes.figure import _draw_skeleton, _view_axes
    motion = data.motion
    index = {n: i for i, n in enumerate(motion.body_names)}
    travel = _view_axes(data)
    side = lambda p: (p[:2] @ travel, p[2])  # noqa: E731
    order = np.argsort(data.psi)
    chosen = order[np.unique(np.linspace(0, len(order) - 1, min(num_motions, len(order))).round().astype(int))]
    colors = plt.get_cmap("viridis")(np.linspace(0.1, 0.9, len(chosen)))
    all_pos = motion.body_pos[None] + data.dense_offsets[chosen][:, :, None, :]
    along = all_pos[..., :2] @ travel
    xlim = (along.min() - 0.3, along.max() + 0.3)
    ylim = (min(0.0, all_pos[..., 2].min()) - 0.1, all_pos[..., 2].max() + 0.2)
    step = max(1, int(round(motion.fps / fps_out)))
    dpi = 80
    fig, ax = plt.subplots(figsize=(size[0] / dpi, size[1] / dpi), dpi=dpi)
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), motion.fps / step, size)
    try:
        for t in range(0, motion.num_frames, step):
            ax.clear()
            ax.set_xlim(*xlim)
            ax.set_ylim(*ylim)
            ax.set_aspect("equal")
            ax.axhline(0.0, color="0.7", lw=0.8)
            for c, n in zip(colors, chosen):
                _draw_skeleton(ax, all_pos[list(chosen).index(n), t], index, side, c, lw=1.5)
            ax.set_title(f"{data.task} D_rule  t={t / motion.fps:.2f}s  ψ=" +
                         ", ".join(f"{data.psi[n]:.2f}" for n in chosen), fontsize=8)
            fig.canvas.draw()
            rgba = np.asarray(fig.canvas.buffer_rgba())
            frame = cv2.cvtColor(rgba[..., :3].copy(), cv2.COLOR_RGB2BGR)
            if frame.shape[1] != size[0] or frame.shape[0] != size[1]:
                frame = cv2.resize(frame, size)
            writer.write(frame)
    finally:
        writer.release()
        plt.close(fig)
    tmp.replace(path)
