"""`adamimic play`: roll out an exported policy at one ψ into an mp4 (or the viewer, with a display).

With a chain (`chain.json`) the video is the whole chain, as a robot runs it: standing on the balance policy,
the go, the task, the balance policy after the handoff. Without one, the task policy alone from its trained
start. Runs the deployment loop of `sim2sim` (ONNX + metadata only) and draws every other control step (25 fps
at 50 Hz control: real time) through the project's renderer (pipeline/render): a side camera following the
pelvis, the edited reference as a blue ghost, and a caption naming the acting policy.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from pipeline.render.mp4 import Mp4Writer
from pipeline.render.reference import ReferencePose
from pipeline.render.renderer import Renderer

STRETCH_CAPTION = {"stand": "balance policy: standing, before the go", "task": "task policy",
                   "balance": "balance policy: after the handoff"}


def _episode(policy_dir: str | Path, task: str | None):
    """(run(psi, on_step, max_steps), Sim2Sim): the export's chain (stand, go, task, balance) when it has
    one, else the task policy alone from its trained start."""
    from pipeline.export.chain import CHAIN_NAME, ChainRunner
    from pipeline.export.sim2sim import Sim2Sim

    if (Path(policy_dir) / CHAIN_NAME).is_file():
        chain = ChainRunner(policy_dir)
        return (lambda psi, on_step, max_steps=None: chain.run(psi, on_step=on_step, visual=True)), chain.task
    runner = Sim2Sim(policy_dir, task=task)
    return (lambda psi, on_step, max_steps=None: runner.run_episode(psi, max_steps=max_steps, on_step=on_step,
                                                                    visual=True)), runner


def caption_lines(task: str, psi: float, stretch: str, phase: float, seconds: float, reached: int,
                  num_keyframes: int) -> list[str]:
    acting = STRETCH_CAPTION[stretch] + (f"  φ {phase:.2f}" if stretch == "task" else "")
    return [f"{task}   ψ {psi:.2f} m   t {seconds:4.1f} s", acting, f"keyframes reached {reached}/{num_keyframes}"]


def play_to_mp4(policy_dir: str | Path, psi: float, out: str | Path = "play.mp4", seconds: float | None = None,
                width: int = 1280, height: int = 720, fps: int = 25, task: str | None = None) -> Path:
    """The whole chain when the export has one, else the task alone; the video stops at `seconds` (None: at
    the episode's end). Returns the mp4's path; its frame count is the control steps shown / (control rate / fps)."""
    run, runner = _episode(policy_dir, task)
    control_hz = 1.0 / runner.control_dt
    every = max(1, int(round(control_hz / fps)))
    max_steps = int(seconds * control_hz) if seconds else None
    reference = ReferencePose.from_metadata(runner.meta)
    keyframe_phases = np.asarray(runner.keyframe_phases)
    state: dict = {"renderer": None, "writer": None, "phase": 0.0}

    def on_step(model, data, info):
        if info.get("stretch") == "task" or "stretch" not in info:
            state["phase"] = float(info["phase"])
        if info["step"] % every or (max_steps is not None and info["step"] > max_steps):
            return
        if state["renderer"] is None:
            state["renderer"] = Renderer(model, width, height)
            state["writer"] = Mp4Writer(out, fps, width, height)
        ghosts = []
        if reference is not None:
            # before the go the ghost waits at the reference's start; after the handoff it rests at its end
            ghosts.append((reference.qpos(model, psi, state["phase"]), None))
        stretch = info.get("stretch", "task")
        reached = info["reached"] if "reached" in info else int(np.sum(keyframe_phases <= state["phase"] + 1e-9))
        caption = caption_lines(runner.meta["task"], psi, stretch, state["phase"], info["step"] * runner.control_dt,
                                reached, len(keyframe_phases))
        state["writer"].add(state["renderer"].frame(data, ghosts=ghosts, caption=caption))

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
