"""`adamimic view PATH`: the pipeline's artifacts in the browser, served on localhost by mjviser (viser).

PATH may be
  * an export folder (`policy.json`, with its chain): the chain running live from the stance at rest: the
    balance policy holds the robot until **go**, the task policy runs, the balance policy takes it back; a ψ
    slider (applied at **restart**, which also moves the terrain to that ψ);
  * a retargeted task folder (`data/retargeted/<task>`, or its `motion/`): the G1 replaying the reference
    and, when `data/human/<task>` is there, the person's joints beside it (the retarget preview's
    placement), with a time slider;
  * a keyframes dataset (`data/keyframes/<task>/d_edit` or `d_rule`): the reference replayed with the edited
    keyframe targets at a ψ slider.
It never opens a browser itself; it prints the address and serves until Ctrl-C.
"""

from __future__ import annotations

import json
import signal
import threading
from pathlib import Path

import mujoco
import numpy as np

from pipeline.common.errors import PipelineInputError

KEYFRAME_RGB = (255, 140, 0)
PERSON_RGB = (60, 120, 220)
ROBOT_EXTENT_M = 1.2  # the scene's size mjviser frames the camera on: the G1, not the terrain


def _server(host: str, port: int):
    import viser

    return viser.ViserServer(host=host, port=port, verbose=False)


def viewer_for(model: mujoco.MjModel, step, server, data: mujoco.MjData | None = None):
    """mjviser's viewer on `server`, stepping with `step(model, data)` in real time. The camera starts about
    3 m from the robot (mjviser places it by the model's extent, which a task's 20 m terrain boxes inflate)."""
    from mjviser import Viewer

    model.stat.extent = ROBOT_EXTENT_M

    return Viewer(model, data if data is not None else mujoco.MjData(model), step_fn=step, server=server)


def _replayer(model: mujoco.MjModel, motion, on_frame=None):
    """(step_fn, state) replaying `motion` in real time; state["frame"] is the frame shown, `state["hold"]`
    pins it (the time slider)."""
    from pipeline.robot.g1 import joint_qpos_indices

    qpos_index = joint_qpos_indices(model, tuple(motion.joint_names))
    state = {"t": 0.0, "frame": 0, "hold": None}

    def step(model, data):
        state["t"] += model.opt.timestep
        frame = state["hold"] if state["hold"] is not None else int(state["t"] * motion.fps) % motion.num_frames
        state["frame"] = frame
        data.qpos[0:3], data.qpos[3:7] = motion.root_pos[frame], motion.root_quat[frame]
        data.qpos[qpos_index] = motion.joint_pos[frame]
        data.qvel[:] = 0.0
        mujoco.mj_kinematics(model, data)
        if on_frame is not None:
            on_frame(frame)

    return step, state


def view_motion(path: Path, server) -> "object":
    """A retargeted motion (and its person) with a time slider."""
    from pipeline.motion.dataset import read_motions
    from pipeline.robot.g1 import build_model

    folder = path.parent if path.name == "motion" else path
    (motion,) = read_motions(folder / "motion")
    model = build_model(visual=True)
    person = None
    human_dir = folder.parent.parent / "human" / folder.name
    if (human_dir / "meta" / "info.json").is_file():
        from pipeline.human.dataset import read_human
        from pipeline.retarget.preview import _human_at

        human = read_human(human_dir)
        person = _human_at(human, motion, 1.32 / human.height)
    slider = server.gui.add_slider("time (s)", 0.0, motion.duration, 1.0 / motion.fps, 0.0)
    follow = server.gui.add_checkbox("play", True)

    def show_person(frame: int) -> None:
        if person is not None:
            server.scene.add_point_cloud("/person", person[frame], PERSON_RGB, point_size=0.04, point_shape="circle")

    step, state = _replayer(model, motion, show_person)

    @slider.on_update
    def _(_event) -> None:
        if not follow.value:
            state["hold"] = int(round(slider.value * motion.fps))

    @follow.on_update
    def _(_event) -> None:
        state["hold"] = None if follow.value else state["frame"]

    return viewer_for(model, step, server)


def view_keyframes(path: Path, server) -> "object":
    """A keyframes dataset: the reference, and the edited keyframe targets of the sample nearest a ψ slider."""
    from pipeline.keyframes.datasets import load_tracking_data
    from pipeline.robot.g1 import build_model

    data = load_tracking_data(path)
    motion = data.motion.reorder_joints(tuple(data.motion.joint_names))
    model = build_model(visual=True)
    psi = server.gui.add_slider("ψ (m)", float(data.psi.min()), float(data.psi.max()), 0.01, float(data.psi_raw))
    frames = np.asarray(data.keyframe_frames)

    def show_targets(_frame: int) -> None:
        sample = int(np.argmin(np.abs(data.psi - psi.value)))
        targets = motion.body_pos[frames] + data.keyframe_offsets[sample][:, None, :]
        server.scene.add_point_cloud("/keyframes", targets.reshape(-1, 3), KEYFRAME_RGB, point_size=0.03,
                                     point_shape="circle")

    step, _ = _replayer(model, motion, show_targets)
    return viewer_for(model, step, server)


def view_export(path: Path, server) -> "object":
    """The export's chain, live: stand until go, the task, the balance policy again."""
    from pipeline.export.chain import ChainRunner, LiveChain

    runner = ChainRunner(path)
    lo, hi = runner.task.meta["psi_limits"]
    live = LiveChain(runner, float(runner.task.meta.get("psi_raw", (lo + hi) / 2)))
    psi = server.gui.add_slider("ψ (m)", float(lo), float(hi), 0.01, live.psi)
    go = server.gui.add_button("go")
    restart = server.gui.add_button("restart")
    status = server.gui.add_markdown(live.status())

    @go.on_click
    def _(_event) -> None:
        live.go()

    @restart.on_click
    def _(_event) -> None:
        live.restart(float(psi.value))

    def step(model, data):
        live.step()
        text = live.status()
        if status.content != text:
            status.content = text

    return viewer_for(live.model, step, server, live.data)


def _is_keyframes_dataset(path: Path) -> bool:
    from pipeline.keyframes.datasets import KIND

    extra = path / "meta" / "pipeline.json"
    return extra.is_file() and json.loads(extra.read_text()).get("kind") == KIND


def serve(path: str | Path, host: str = "127.0.0.1", port: int = 8080, log=print) -> None:
    """Serves PATH (see the module docstring) until Ctrl-C."""
    path = Path(path)
    if not path.exists():
        raise PipelineInputError(path, None, "nothing to view here (an export folder, data/retargeted/<task> or a "
                                 "keyframes dataset)")
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C (SIGINT) stops it even when started where SIGINT is ignored (a shell's background job)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    server = _server(host, port)
    try:
        if (path / "policy.json").is_file():
            viewer = view_export(path, server)
        elif (path / "motion").is_dir() or path.name == "motion":
            viewer = view_motion(path, server)
        elif _is_keyframes_dataset(path):
            viewer = view_keyframes(path, server)
        else:
            raise PipelineInputError(path, None, "not an export folder, a retargeted task or a keyframes dataset")
        log(f"adamimic view: serving {path} at http://{host}:{server.get_port()} (Ctrl-C stops)")
        viewer.run()
    except BaseException:  # a bad path, or Ctrl-C before mjviser's loop has its handler: viser's threads would outlive us
        server.stop()
        raise
