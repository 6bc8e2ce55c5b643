"""Everything the keyframes stage writes for one task, from its (retargeted, 50 fps) motion:
D_edit, D_rule (LeRobot layout), the keyframe table (json), the figure (png) and the D_rule video.
All checks (keyframes, edits, terrain) run before the first write."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.common.atomic import write_text_atomic
from pipeline.keyframes.config import TaskConfig
from pipeline.keyframes.datasets import write_tracking_dataset
from pipeline.keyframes.edit import build_tracking_data
from pipeline.keyframes.figure import keyframe_figure, rule_video
from pipeline.keyframes.select import select_keyframes
from pipeline.motion.motion import Motion


def build_task_outputs(motion: Motion, task: TaskConfig, out_dir: str | Path, num_samples: int | None = None,
                       seed: int | None = None, video: bool = True) -> dict[str, Path]:
    out_dir = Path(out_dir)
    table = select_keyframes(motion, task)
    edit = build_tracking_data(motion, task, table, "edit", num_samples, seed)
    rule = build_tracking_data(motion, task, table, "rule", num_samples, seed)
    paths = {"d_edit": out_dir / "d_edit", "d_rule": out_dir / "d_rule", "keyframes": out_dir / "keyframes.json",
             "figure": out_dir / "keyframes.png"}
    write_tracking_dataset(paths["d_edit"], edit)
    write_tracking_dataset(paths["d_rule"], rule)
    write_text_atomic(paths["keyframes"], json.dumps({"task": task.name, **table.to_dict(), "terrain": edit.terrain},
                                                     indent=1))
    keyframe_figure(edit, paths["figure"])
    if video:
        paths["video"] = out_dir / "d_rule.mp4"
        rule_video(rule, paths["video"])
    return paths
