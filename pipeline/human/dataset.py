"""`HumanMotion` <-> a LeRobot v3.0 dataset (one episode), through `pipeline.dataset.lerobot`.

Frame features (float64, so a round trip is exact): `human.joint_pos` (22, 3) world z-up,
`human.joint_quat` (22, 4) global wxyz, `human.local_rotvec` (22, 3), `human.root_trans` (3,).
Clip-level facts (name, source, height, betas, joint names/parents, frame convention) go to
`meta/pipeline.json` (`extra`). The task string is "human motion: <name>".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.human.motion import SMPL_JOINT_NAMES, SMPL_PARENTS, HumanMotion

KIND = "human_motion"
FRAME = "world z-up, metres, floor z=0, facing +x at start; quaternions wxyz; SMPL joint order"
AXES = ["x", "y", "z"]


def _features(joint_names: tuple[str, ...]):
    from pipeline.dataset.lerobot import Feature

    joints = list(joint_names)
    return {
        "human.joint_pos": Feature("float64", (len(joints), 3), {"joints": joints, "axes": AXES}),
        "human.joint_quat": Feature("float64", (len(joints), 4), {"joints": joints, "axes": ["w", "x", "y", "z"]}),
        "human.local_rotvec": Feature("float64", (len(joints), 3), {"joints": joints, "axes": AXES}),
        "human.root_trans": Feature("float64", (3,), AXES),
    }


def write_human(path: str | Path, motion: HumanMotion) -> None:
    """Writes the clip atomically (the dataset writer stages and swaps the directory)."""
    from pipeline.dataset.lerobot import write_dataset

    episode = {
        "human.joint_pos": motion.joint_pos,
        "human.joint_quat": motion.joint_quat,
        "human.local_rotvec": motion.local_rotvec,
        "human.root_trans": motion.root_trans,
    }
    extra = {
        "kind": KIND,
        "name": motion.name,
        "source": motion.source,
        "height": float(motion.height),
        "betas": [float(b) for b in motion.betas],
        "joint_names": list(motion.joint_names),
        "parents": list(SMPL_PARENTS),
        "frame": FRAME,
    }
    write_dataset(
        path, fps=float(motion.fps), features=_features(motion.joint_names), episodes=[episode],
        tasks=[f"human motion: {motion.name}"], robot_type="smpl_human", extra=extra,
    )


def read_human(path: str | Path) -> HumanMotion:
    from pipeline.dataset.lerobot import read_dataset

    data = read_dataset(path)
    extra = data.extra or {}
    if extra.get("kind") != KIND:
        raise PipelineInputError(path, "meta/pipeline.json.kind", f"expected {KIND!r}, got {extra.get('kind')!r}")
    if len(data.episodes) != 1:
        raise PipelineInputError(path, "episodes", f"a human motion has one episode, found {len(data.episodes)}")
    names = tuple(extra.get("joint_names", SMPL_JOINT_NAMES))
    if names != SMPL_JOINT_NAMES:
        raise PipelineInputError(path, "meta/pipeline.json.joint_names", "not the 22 SMPL body joints in SMPL order")
    episode = data.episodes[0]
    for key in _features(names):
        if key not in episode:
            raise PipelineInputError(path, key, "missing feature")
    try:
        return HumanMotion(
            fps=float(data.fps),
            joint_pos=episode["human.joint_pos"],
            joint_quat=episode["human.joint_quat"],
            local_rotvec=episode["human.local_rotvec"],
            root_trans=episode["human.root_trans"],
            betas=np.asarray(extra.get("betas", np.zeros(10)), dtype=np.float64),
            height=float(extra.get("height", 1.7)),
            name=str(extra.get("name", Path(path).name)),
            source=str(extra.get("source", path)),
        )
    except PipelineInputError as exc:
        raise PipelineInputError(path, exc.field, exc.problem) from None
