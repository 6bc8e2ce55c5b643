"""`adamimic play`: roll out an exported policy at one ψ into an mp4 (or the viewer, with a display).

Runs the deployment loop of `sim2sim` (ONNX + metadata only) and renders every other control step
(25 fps at 50 Hz control), the keyframe targets drawn as spheres: orange until reached, then green.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from pipeline.evaluation.video import MARKER_RGBA_PENDING, MARKER_RGBA_REACHED, Mp4Writer, SceneRenderer
from pipeline.export.sim2sim import Sim2Sim


def _episode(policy_dir: str | Path, task: str | None):
    """(run(psi, on_step, max_steps), Sim2Sim): the export's chain (stand, go, task, balance) when it has
    one, else the task policy alone from its trained start."""
    from pipeline.export.chain import CHAIN_NAME, ChainRunner

    if (Path(policy_dir) / CHAIN_NAME).is_file():
        chain = ChainRunner(policy_dir)
        return (lambda psi, on_step, max_steps=None: chain.run(psi, on_step=on_step, visual=True)), chain.task
    runner = Sim2Sim(policy_dir, task=task)
    return (lambda psi, on_step, max_steps=None: runner.run_episode(psi, max_steps=max_steps, on_step=on_step,
                                                                    visual=True)), runner


def play_to_mp4(policy_dir: str | Path, psi: float, out: str | Path = "play.mp4", seconds: float | None = None,
                width: int = 640, height: int = 480, fps: int = 25, task: str | None = None) -> Path:
    """The whole chain when the export has one (seconds: ignored), else the task alone (cut at `seconds`)."""
    run, runner = _episode(policy_dir, task)
    control_hz = 1.0 / runner.control_dt
    every = max(1, int(round(control_hz / fps)))
    max_steps = int(seconds * control_hz) if seconds else None
    state: dict = {"renderer": None, "writer": None}
    targets = runner.keyframe_targets(psi)  # (K, B, 3)
    kf_phases = runner.keyframe_phases

    def on_step(model, data, info):
        if info["step"] % every:
            return
        if state["renderer"] is None:
            state["renderer"] = SceneRenderer(model, width, height)
            state["writer"] = Mp4Writer(out, fps, width, height)
        reached = np.arange(len(kf_phases)) < info["reached"] if "reached" in info else kf_phases <= info["phase"] + 1e-12
        colors = np.where(reached[:, None], MARKER_RGBA_REACHED, MARKER_RGBA_PENDING)  # (K, 4)
        colors = np.broadcast_to(colors[:, None], targets.shape[:2] + (4,))
        frame = state["renderer"].render(data, targets.reshape(-1, 3), colors.reshape(-1, 4), 0.03)
        state["writer"].add(frame)

    try:
        run(psi, on_step, max_steps)
    finally:
        if state["renderer"] is not None:
            state["renderer"].close()
    if state["writer"] is None:
        raise RuntimeError("the episode ended before the first rendered frame")
    return state["writer"].close()


def play_viewer(policy_dir: str | Path, psi: float, task: str | None = None) -> None:
    """Interactive viewer (needs a display); real-time pacing."""
    import mujoco.viewer

    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise RuntimeError("no display: use play_to_mp4")
    run, runner = _episode(policy_dir, task)
    handle = {}

    def on_step(model, data, info):
        if "viewer" not in handle:
            handle["viewer"] = mujoco.viewer.launch_passive(model, data)
        handle["viewer"].sync()
        time.sleep(runner.control_dt)

    run(psi, on_step)
