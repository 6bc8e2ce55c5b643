"""What a frame of the project's videos costs on this machine, per resolution.

    .venv/bin/python benchmarks/render_cost.py [EXPORT_DIR] [--frames 100]

Replays one chain of an export (default: models/pretrained/far_jump_rest/export at ψ 1.0) once, keeps every
other control step's MuJoCo state (25 fps, as `adamimic play` and the evaluate stage draw), then draws those
states through pipeline/render (styled scene, shadow, the reference ghost, the caption) and encodes them to
H.264, at each resolution (and once without the shadow). Prints, per resolution, the frames per second of rendering alone and of rendering +
encoding, and the ratio to real time (25 fps): 1.0 means a clip takes as long to make as to watch. The physics
is not timed. MUJOCO_GL is whatever importing `pipeline` chose (EGL on llvmpipe without a GPU).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import pipeline  # noqa: E402,F401  (chooses MUJOCO_GL before mujoco is first imported)

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from pipeline.export.chain import ChainRunner  # noqa: E402
from pipeline.export.play import caption_lines  # noqa: E402
from pipeline.render.mp4 import Mp4Writer  # noqa: E402
from pipeline.render.reference import ReferencePose  # noqa: E402
from pipeline.render.renderer import Renderer  # noqa: E402

# (width, height, shadows): the videos' settings are 1280x720 with the shadow
RESOLUTIONS = ((640, 480, True), (960, 540, True), (1280, 720, True), (1280, 720, False))
FPS = 25


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("export", nargs="?", default="models/pretrained/far_jump_rest/export")
    parser.add_argument("--psi", type=float, default=1.0)
    parser.add_argument("--frames", type=int, default=100)
    args = parser.parse_args()

    chain = ChainRunner(args.export)
    reference = ReferencePose.from_metadata(chain.task.meta)
    states, scene = [], {}

    def keep(model, data, info):
        scene["model"] = model
        if info["step"] % 2 == 0 and len(states) < args.frames:
            states.append((data.qpos.copy(), info.get("phase") or 0.0, info["stretch"]))

    chain.run(args.psi, on_step=keep, visual=True)
    model = scene["model"]
    data = mujoco.MjData(model)
    print(f"MUJOCO_GL={os.environ.get('MUJOCO_GL')} cores={os.cpu_count()} frames={len(states)} "
          f"ghost={'yes' if reference is not None else 'no (export without the reference pose)'}")
    for width, height, shadows in RESOLUTIONS:
        renderer = Renderer(model, width, height, shadows=shadows)
        frames, start = [], time.perf_counter()
        for qpos, phase, stretch in states:
            data.qpos[:] = qpos
            mujoco.mj_kinematics(model, data)
            ghosts = [(reference.qpos(model, args.psi, phase), None)] if reference is not None else []
            frames.append(renderer.frame(data, ghosts=ghosts,
                                         caption=caption_lines("task", args.psi, stretch, phase, 0.0, 0, 5)))
        render_s = time.perf_counter() - start
        renderer.close()
        with tempfile.TemporaryDirectory() as scratch:
            writer = Mp4Writer(Path(scratch) / "clip.mp4", FPS, width, height)
            start = time.perf_counter()
            for frame in frames:
                writer.add(frame)
            writer.close()
            encode_s = time.perf_counter() - start
        n = len(frames)
        print(f"{width}x{height}{'' if shadows else ' no shadow'}: render {n / render_s:5.1f} fps, render+encode {n / (render_s + encode_s):5.1f} fps, "
              f"ratio to real time {n / (render_s + encode_s) / FPS:.2f}")


if __name__ == "__main__":
    main()
