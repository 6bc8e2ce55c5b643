"""Everything the keyframes stage writes for one task, from its (retargeted, 50 fps) motion cut to the task's
`clip` window:
D_edit, D_rule (LeRobot layout), the keyframe table (json), the figure (png) and the D_rule video.
All checks (keyframes, edits, terrain) run before the first write."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.common.atomic import write_text_atomic
from pipeline.keyframes.config import TaskConfig
from pipeline.keyframes.datasets import write_tracking_dataset
from pipeline.keyframes.edit import build_tracking_data
from pipeline.keyframes.figure import keyframe_figure
from pipeline.keyframes.rule_video import rule_video
from pipeline.keyframes.lead_in import with_lead_in
from pipeline.keyframes.select import select_keyframes
from pipeline.motion.motion import Motion


def build_task_outputs(motion: Motion, task: TaskConfig, out_dir: str | Path, num_samples: int | None = None,
                       seed: int | None = None, video: bool = True) -> dict[str, Path]:
    out_dir = Path(out_dir)
    start, stop = task.clip.frames(motion.fps, motion.num_frames, task.name)
    window = {}
    if (start, stop) != (0, motion.num_frames):  # a slice renormalises quaternions: the whole clip stays as read
        window = {"clip": {"start_s": start / motion.fps, "end_s": (stop - 1) / motion.fps, "frames": [start, stop]}}
        motion = motion.slice(start, stop)
    table = select_keyframes(motion, task)
    edit = build_tracking_data(motion, task, table, "edit", num_samples, seed)
    rule = build_tracking_data(motion, task, table, "rule", num_samples, seed)
    if task.clip.lead_in_s > 0:  # from the stance at rest; the table's frames stay the window's (keyframes.json says)
        edit, rule = with_lead_in(edit, task.clip.lead_in_s), with_lead_in(rule, task.clip.lead_in_s)
        frames = int(round(task.clip.lead_in_s * motion.fps))
        window["lead_in"] = {"seconds": frames / motion.fps, "frames": frames,
                             "note": "the datasets' frames are this table's plus `frames`"}
    paths = {"d_edit": out_dir / "d_edit", "d_rule": out_dir / "d_rule", "keyframes": out_dir / "keyframes.json",
             "figure": out_dir / "keyframes.png"}
    write_tracking_dataset(paths["d_edit"], edit)
    write_tracking_dataset(paths["d_rule"], rule)
    write_text_atomic(paths["keyframes"], json.dumps({"task": task.name, **window, **table.to_dict(), "terrain": edit.terrain},
                                                     indent=1))
    keyframe_figure(edit, paths["figure"], flights=list(table.flights))
    if video:
        paths["video"] = out_dir / "d_rule.mp4"
        rule_video(rule, paths["video"])
    return paths


def paper_task_figures(out_dir: str | Path, shared_dir: str | Path) -> list[Path]:
    """The keyframing figure of every paper task whose input is present: import, retarget, select,
    edit, draw. `python -m pipeline.keyframes.outputs OUT_DIR [SHARED_DIR]`."""
    from pipeline.config import paper_tasks
    from pipeline.human.importers import load_human_motion
    from pipeline.keyframes.config import TaskConfig
    from pipeline.retarget import RetargetConfig, retarget

    written = []
    for name, raw in paper_tasks().items():
        clip = Path(shared_dir) / f"{name}.npz"
        if not clip.is_file():
            continue
        task = TaskConfig.from_dict(name, {**raw, "input": str(clip)})
        motion, _ = retarget(load_human_motion(clip), RetargetConfig(), progress=False)
        table = select_keyframes(motion, task)
        path = Path(out_dir) / f"keyframes_{name}.png"
        keyframe_figure(build_tracking_data(motion, task, table, "edit", None, 0), path, flights=list(table.flights))
        written.append(path)
    return written


if __name__ == "__main__":
    import sys

    from pipeline import REPO_ROOT

    shared = sys.argv[2] if len(sys.argv) > 2 else REPO_ROOT.parent / "shared" / "data" / "adamimic_smpl"
    for figure in paper_task_figures(sys.argv[1], shared):
        print(figure)
