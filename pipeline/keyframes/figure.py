"""The "keyframing and editing" picture: the original keyframes' skeletons in grey and the moved ones
coloured by ψ (blues: easy, reds: hard), in a side view (along the travel vs height) and a top view,
each flight's path drawn over the root's and numbered with its take-off and landing times. The D_rule
video: keyframes/rule_video.py."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.common.atomic import atomic_file  # noqa: E402
from pipeline.keyframes.tracking_data import TrackingData  # noqa: E402

BONES = (
    ("pelvis", "left_hip"), ("left_hip", "left_knee"), ("left_knee", "left_ankle"),
    ("pelvis", "right_hip"), ("right_hip", "right_knee"), ("right_knee", "right_ankle"),
    ("pelvis", "torso"), ("torso", "head"),
    ("torso", "left_collar"), ("left_collar", "left_shoulder"), ("left_shoulder", "left_elbow"),
    ("left_elbow", "left_wrist"),
    ("torso", "right_collar"), ("right_collar", "right_shoulder"), ("right_shoulder", "right_elbow"),
    ("right_elbow", "right_wrist"),
)


def _in_ranges(value: float, ranges) -> bool:
    return any(lo <= value <= hi for lo, hi in ranges)


def _pick_samples(data: TrackingData, per_group: int = 3) -> list[tuple[int, str]]:
    """A few samples spread over the easy and the hard ranges."""
    picked = []
    for group in ("easy", "hard"):
        ranges = data.psi_ranges.get(group, [])
        idx = [i for i, p in enumerate(data.psi) if _in_ranges(p, ranges)]
        if idx:
            order = sorted(idx, key=lambda i: data.psi[i])
            take = np.unique(np.linspace(0, len(order) - 1, min(per_group, len(order))).round().astype(int))
            picked += [(order[j], group) for j in take]
    return picked


def _view_axes(data: TrackingData) -> np.ndarray:
    """Unit horizontal travel direction of the clip (side view's abscissa)."""
    travel = data.motion.root_pos[-1, :2] - data.motion.root_pos[0, :2]
    n = np.linalg.norm(travel)
    return travel / n if n > 0.05 else np.array([1.0, 0.0])


def _draw_skeleton(ax, pos: np.ndarray, index: dict, project, color, alpha=1.0, lw=1.2) -> None:
    for a, b in BONES:
        if a in index and b in index:
            pa, pb = project(pos[index[a]]), project(pos[index[b]])
            ax.plot([pa[0], pb[0]], [pa[1], pb[1]], color=color, alpha=alpha, lw=lw, solid_capstyle="round")


def _flights_of(data: TrackingData) -> list[tuple[int, int]]:
    """(take-off, landing) frames paired from the keyframe labels (takeoff_k with landing_k)."""
    frame_of = dict(zip(data.keyframe_labels, (int(f) for f in data.keyframe_frames)))
    out = []
    for label, takeoff in frame_of.items():
        if label.startswith("takeoff"):
            landing = frame_of.get("landing" + label[len("takeoff"):])
            if landing is not None and landing > takeoff:
                out.append((takeoff, landing))
    return sorted(out)


def keyframe_figure(data: TrackingData, path: str | Path, title: str | None = None,
                    flights: list[tuple[int, int]] | None = None) -> None:
    """Writes the png (atomically). `flights`: (take-off, landing) frames (default: from the labels)."""
    flights = _flights_of(data) if flights is None else [tuple(int(x) for x in f) for f in flights]
    motion = data.motion
    index = {n: i for i, n in enumerate(motion.body_names)}
    travel = _view_axes(data)
    side = lambda p: (p[:2] @ travel, p[2])  # noqa: E731
    top = lambda p: (p[0], p[1])  # noqa: E731
    fig, axes = plt.subplots(2, 1, figsize=(11, 7), gridspec_kw={"height_ratios": [1.2, 1]})
    samples = _pick_samples(data)
    cmaps = {"easy": plt.get_cmap("Blues"), "hard": plt.get_cmap("Reds")}
    for ax, project in ((axes[0], side), (axes[1], top)):
        ax.plot(*np.array([project(p) for p in motion.root_pos]).T, color="0.8", lw=0.8, ls="--")
        for i, (takeoff, landing) in enumerate(flights):
            path_xy = np.array([project(p) for p in motion.root_pos[takeoff:landing + 1]])
            ax.plot(*path_xy.T, color="darkorange", lw=2.5, alpha=0.8, solid_capstyle="round")
            if project is side:  # numbered above the skeletons, at the flight's middle
                ax.text(path_xy[:, 0].mean(), 1.02, f"{i + 1}: {takeoff / motion.fps:.2f}-{landing / motion.fps:.2f} s",
                        transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=7, color="darkorange")
        for k, frame in enumerate(data.keyframe_frames):
            _draw_skeleton(ax, motion.body_pos[frame], index, project, "0.55", alpha=0.8)
        for j, (n, group) in enumerate(samples):
            group_members = [s for s in samples if s[1] == group]
            shade = 0.45 + 0.5 * group_members.index((n, group)) / max(len(group_members) - 1, 1)
            color = cmaps[group](shade)
            for k, frame in enumerate(data.keyframe_frames):
                off = data.keyframe_offsets[n, k]
                if np.allclose(off, 0.0):
                    continue  # unmoved: it is the grey one
                _draw_skeleton(ax, motion.body_pos[frame] + off, index, project, color, lw=1.0)
        ax.set_aspect("equal")
        ax.grid(alpha=0.2)
    axes[0].set_xlabel("along the travel (m)")
    axes[0].set_ylabel("height (m)")
    axes[1].set_xlabel("x (m)")
    axes[1].set_ylabel("y (m)")
    handles = [plt.Line2D([], [], color="0.55", label=f"original keyframes (ψ_raw = {data.psi_raw:g})")]
    if flights:
        handles.append(plt.Line2D([], [], color="darkorange", lw=2.5, label=f"root in flight ({len(flights)} flights)"
                                  if len(flights) > 1 else "root in flight"))
    handles += [plt.Line2D([], [], color=cmaps[g](0.7), label=f"{g}: ψ = " + ", ".join(
        f"{data.psi[n]:.2f}" for n, gg in samples if gg == g)) for g in ("easy", "hard")
        if any(gg == g for _, gg in samples)]
    axes[0].legend(handles=handles, loc="upper left", fontsize=8)
    edited = [f"{data.keyframe_frames[k] / motion.fps:.2f}s {data.keyframe_labels[k]}".strip()
              for k in np.flatnonzero(data.edited)]
    fig.suptitle(title or f"{data.task}: {data.num_keyframes} keyframes, {len(flights)} flight(s), "
                 f"edited {', '.join(edited)}")
    fig.tight_layout()
    path = Path(path)
    with atomic_file(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=110)
    plt.close(fig)
