"""`Motion` <-> LeRobot v3.0 dataset: one episode per motion, the motion's name as its task.

Features (float64, so a write -> read round trip is bit-exact):
  root_pos (3,) names x,y,z | root_quat (4,) names w,x,y,z | joint_pos (J,) names = joint names |
  body_pos (B, 3) and body_quat (B, 4) names = tracked-body names.
Velocities are not stored: `Motion` derives them from the poses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.dataset.lerobot import Feature, read_dataset, write_dataset
from pipeline.motion.motion import Motion

MOTION_FEATURES = ("root_pos", "root_quat", "joint_pos", "body_pos", "body_quat")
DTYPE = "float64"


def motion_features(joint_names, body_names) -> dict[str, Feature]:
    joint_names, body_names = list(joint_names), list(body_names)
    return {
        "root_pos": Feature(DTYPE, (3,), ["x", "y", "z"]),
        "root_quat": Feature(DTYPE, (4,), ["w", "x", "y", "z"]),
        "joint_pos": Feature(DTYPE, (len(joint_names),), joint_names),
        "body_pos": Feature(DTYPE, (len(body_names), 3), body_names),
        "body_quat": Feature(DTYPE, (len(body_names), 4), body_names),
    }


def write_motions(path: str | Path, motions: list[Motion], extra: dict | None = None) -> None:
    """Writes motions (same fps, joints and bodies) as one dataset, atomically."""
    path = Path(path)
    if not motions:
        raise PipelineInputError(path, "motions", "nothing to write")
    first = motions[0]
    for i, motion in enumerate(motions):
        motion.validate()
        if motion.fps != first.fps:
            raise PipelineInputError(motion.source, "fps", f"motion {i} at {motion.fps} fps, motion 0 at {first.fps}: "
                                     "one dataset has one rate (resample first)")
        if motion.joint_names != first.joint_names:
            raise PipelineInputError(motion.source, "joint_names", f"motion {i} names other joints than motion 0")
        if motion.body_names != first.body_names:
            raise PipelineInputError(motion.source, "body_names", f"motion {i} names other bodies than motion 0")
    episodes = [{key: getattr(m, key) for key in MOTION_FEATURES} for m in motions]
    write_dataset(
        path,
        fps=first.fps,
        features=motion_features(first.joint_names, first.body_names),
        episodes=episodes,
        tasks=[m.name for m in motions],
        extra=extra,
    )


def _names(data, path: Path, key: str, count: int) -> tuple[str, ...]:
    names = data.features[key].names
    if not isinstance(names, list) or len(names) != count or not all(isinstance(n, str) for n in names):
        raise PipelineInputError(path / "meta/info.json", f"features.{key}.names", f"need {count} names, got {names!r}")
    return tuple(names)


def read_motions(path: str | Path) -> list[Motion]:
    path = Path(path)
    data = read_dataset(path)
    for key in MOTION_FEATURES:
        if key not in data.features:
            raise PipelineInputError(path / "meta/info.json", f"features.{key}", "missing: not a motion dataset")
    joint_names = _names(data, path, "joint_pos", data.features["joint_pos"].shape[0])
    body_names = _names(data, path, "body_pos", data.features["body_pos"].shape[0])
    motions = []
    for episode, task in zip(data.episodes, data.tasks):
        motion = Motion(
            fps=data.fps, joint_names=joint_names, body_names=body_names,
            name=task, source=str(path), **{key: episode[key] for key in MOTION_FEATURES},
        )
        # Motion re-normalises quaternions, which may move the last bit of ones a Motion already
        # normalised when it was written; keep the stored values when they are unit and continuous.
        for key in ("root_quat", "body_quat"):
            stored = np.asarray(episode[key], dtype=np.float64)
            if np.allclose(stored, getattr(motion, key), rtol=0.0, atol=1e-12):
                setattr(motion, key, stored.copy())
        motions.append(motion)
    return motions
