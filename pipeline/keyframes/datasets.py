"""D_edit / D_rule on disk (LeRobot v3.0 layout) and back to `TrackingData`.

One episode per sampled ψ. Frame columns (float64 so a round trip is exact): the edited reference
(root_pos, root_quat, joint_pos, body_pos, body_quat, as `pipeline.motion.dataset`), `offset` (3,)
the world translation applied at that frame (D_edit: the latest keyframe's, D_rule: the dense one),
`psi` (1,) constant in the episode, `keyframe_index` (1,) the keyframe on that frame or −1.
`meta/pipeline.json` (`extra`) holds the keyframe table, ψ_raw, ψ ranges, terrain and the mode.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.dataset.lerobot import Feature, read_dataset, write_dataset
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.motion.dataset import MOTION_FEATURES, motion_features
from pipeline.motion.motion import Motion

KIND = "adamimic_tracking_data"


def frame_offsets(data: TrackingData) -> np.ndarray:
    """(N, T, 3) the offset of every frame of every sample (what the environment tracks)."""
    t = data.motion.num_frames
    frames = np.arange(t)
    return np.stack([data.offsets_at_frames(np.full(t, n), frames) for n in range(data.num_samples)])


def write_tracking_dataset(path: str | Path, data: TrackingData, mode: str | None = None) -> None:
    """Writes D_edit (no dense offsets) or D_rule (dense offsets) atomically."""
    mode = mode or ("rule" if data.dense_offsets is not None else "edit")
    motion = data.motion
    offsets = frame_offsets(data)
    keyframe_index = np.full(motion.num_frames, -1, dtype=np.int64)
    keyframe_index[data.keyframe_frames] = np.arange(data.num_keyframes)
    features = motion_features(motion.joint_names, motion.body_names)
    features.update({
        "offset": Feature("float64", (3,), ["x", "y", "z"]),
        "psi": Feature("float64", (1,), ["psi"]),
        "keyframe_index": Feature("int64", (1,), ["keyframe_index"]),
    })
    episodes = []
    for n in range(data.num_samples):
        off = offsets[n]
        episodes.append({
            "root_pos": motion.root_pos + off,
            "root_quat": motion.root_quat,
            "joint_pos": motion.joint_pos,
            "body_pos": motion.body_pos + off[:, None, :],
            "body_quat": motion.body_quat,
            "offset": off,
            "psi": np.full((motion.num_frames, 1), data.psi[n]),
            "keyframe_index": keyframe_index[:, None],
        })
    extra = {
        "kind": KIND,
        "mode": mode,
        "task": data.task,
        "motion_name": motion.name,
        "psi_raw": data.psi_raw,
        "psi_ranges": {k: [list(r) for r in v] for k, v in data.psi_ranges.items()},
        "terrain": data.terrain,
        "keyframes": {
            "frames": data.keyframe_frames.tolist(),
            "times": (data.keyframe_frames / motion.fps).tolist(),
            "labels": list(data.keyframe_labels),
            "edited": data.edited.tolist(),
            "sparse_scale": data.sparse_scale.tolist(),
        },
    }
    write_dataset(path, fps=motion.fps, features=features, episodes=episodes,
                  tasks=[f"{data.task} psi={p:.4f}" for p in data.psi], extra=extra)


def load_tracking_data(path: str | Path) -> TrackingData:
    path = Path(path)
    ds = read_dataset(path)
    extra = ds.extra or {}
    if extra.get("kind") != KIND:
        raise PipelineInputError(path / "meta/pipeline.json", "kind", f"not a D_edit/D_rule dataset (kind {extra.get('kind')!r})")
    for key in (*MOTION_FEATURES, "offset", "psi"):
        if key not in ds.features:
            raise PipelineInputError(path / "meta/info.json", f"features.{key}", "missing")
    kf = extra["keyframes"]
    frames = np.asarray(kf["frames"], dtype=int)
    first = ds.episodes[0]
    t = first["root_pos"].shape[0]
    if len(frames) == 0 or np.any(np.diff(frames) <= 0) or frames[-1] >= t or frames[0] < 0:
        raise PipelineInputError(path / "meta/pipeline.json", "keyframes.frames", f"bad keyframe frames {frames.tolist()}")
    offsets = np.stack([ep["offset"] for ep in ds.episodes])  # (N, T, 3)
    off0 = offsets[0]
    motion = Motion(
        fps=ds.fps,
        joint_names=tuple(ds.features["joint_pos"].names),
        body_names=tuple(ds.features["body_pos"].names),
        root_pos=first["root_pos"] - off0,
        root_quat=first["root_quat"],
        joint_pos=first["joint_pos"],
        body_pos=first["body_pos"] - off0[:, None, :],
        body_quat=first["body_quat"],
        name=extra.get("motion_name", extra.get("task", "motion")),
        source=str(path),
    )
    for key in ("root_quat", "body_quat"):  # keep the stored unit quaternions bit for bit
        stored = np.asarray(first[key], dtype=np.float64)
        if np.allclose(stored, getattr(motion, key), rtol=0.0, atol=1e-12):
            setattr(motion, key, stored.copy())
    return TrackingData(
        task=extra["task"],
        motion=motion,
        keyframe_frames=frames,
        keyframe_labels=tuple(kf["labels"]),
        sparse_scale=np.asarray(kf["sparse_scale"], float),
        edited=np.asarray(kf["edited"], bool),
        psi=np.array([ep["psi"][0, 0] for ep in ds.episodes]),
        keyframe_offsets=offsets[:, frames],
        dense_offsets=offsets if extra.get("mode") == "rule" else None,
        psi_raw=float(extra["psi_raw"]),
        psi_ranges={k: [tuple(r) for r in v] for k, v in extra.get("psi_ranges", {}).items()},
        terrain=extra.get("terrain") or {},
    )
