"""The results page's images: the success-vs-ψ plot, the keyframe figure scaled to the page, a rollout
video as a GIF, each kept under a size the repository can carry."""

from __future__ import annotations

import io
import math
from pathlib import Path

from pipeline.common.atomic import atomic_file
from pipeline.common.errors import PipelineInputError

MAX_IMAGE_BYTES = 300_000  # every still image this page commits stays below this
MAX_GIF_BYTES = 2_000_000  # and every rollout GIF
KEYFRAMES_WIDTH = 900  # px, the keyframe figure's width on the page
GIF_WIDTH = 640  # px, the rollout GIF's width
GIF_FPS = 5  # frames a second of the rollout kept (the whole chain: standing, the go, the task, the stand)


def _save_png(image, path: Path) -> None:
    """PNG of a PIL image, reduced to a palette (and then halved) until it fits MAX_IMAGE_BYTES."""
    while True:
        buf = io.BytesIO()
        image.convert("RGB").quantize(colors=128).save(buf, format="PNG", optimize=True)
        if buf.tell() <= MAX_IMAGE_BYTES or image.width < 200:
            break
        image = image.resize((image.width // 2, image.height // 2))
    with atomic_file(path, "wb") as handle:
        handle.write(buf.getvalue())


def plot_success_vs_psi(entries: list, path: Path) -> bool:
    """Success (%) against ψ, one line per variant (results_page.Evaluated), the easy and hard ranges shaded
    and ψ_raw marked.
    False (nothing written) when no entry has a per_psi.csv."""
    with_rows = [e for e in entries if e.per_psi]
    if not with_rows:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    fig, ax = plt.subplots(figsize=(5.6, 3.0))
    shades = {"easy": "#d8f0d8", "hard": "#f6dcdc"}
    for name, intervals in with_rows[0].metrics["psi_ranges"].items():
        for k, (lo, hi) in enumerate(intervals):
            ax.axvspan(lo, hi, color=shades.get(name, "#eeeeee"), zorder=0, label=f"{name} range" if k == 0 else None)
    psi_raw = with_rows[0].metrics.get("psi_raw")
    if isinstance(psi_raw, (int, float)) and math.isfinite(psi_raw):
        ax.axvline(psi_raw, color="0.4", ls="--", lw=1, label=f"clip's own ψ {psi_raw:.2f}")
    for entry in with_rows:
        ax.plot([r["psi"] for r in entry.per_psi], [r["success"] for r in entry.per_psi], "o-", ms=3,
                label=entry.variant)
    ax.set_xlabel("ψ (m)")
    ax.set_ylabel("success (%)")
    ax.set_ylim(-3, 103)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    buf.seek(0)
    _save_png(Image.open(buf), path)
    return True


def copy_keyframes_figure(source: Path, path: Path) -> bool:
    """The keyframes stage's figure, scaled to KEYFRAMES_WIDTH. False when the stage's output is absent."""
    if not source.is_file():
        return False
    from PIL import Image

    image = Image.open(source)
    if image.width > KEYFRAMES_WIDTH:
        image = image.resize((KEYFRAMES_WIDTH, round(image.height * KEYFRAMES_WIDTH / image.width)))
    _save_png(image, path)
    return True


def rollout_video(media: Path) -> Path | None:
    """The rollout to show: an easy-range one if there is one (the task's main case), else the first."""
    videos = sorted(media.glob("*.mp4")) if media.is_dir() else []
    easy = [v for v in videos if v.name.startswith("easy")]
    return (easy or videos or [None])[0]


def video_to_gif(video: Path, path: Path) -> None:
    """GIF_FPS frames a second sampled evenly over the whole video, GIF_WIDTH wide, played in real time;
    fewer frames until it fits MAX_GIF_BYTES."""
    import av
    from PIL import Image

    with av.open(str(video)) as container:
        frames = [frame.to_image() for frame in container.decode(video=0)]
    if not frames:
        raise PipelineInputError(video, None, "holds no video frames")
    count = min(len(frames), max(2, round(GIF_FPS * _video_seconds(video, len(frames)))))
    while True:
        picked = [frames[round(i * (len(frames) - 1) / max(count - 1, 1))] for i in range(count)]
        small = [f.resize((GIF_WIDTH, round(f.height * GIF_WIDTH / f.width))).convert("P", palette=Image.ADAPTIVE)
                 for f in picked]
        buf = io.BytesIO()
        duration_ms = max(40, round(1000 * _video_seconds(video, len(frames)) / count))
        small[0].save(buf, format="GIF", save_all=True, append_images=small[1:], duration=duration_ms, loop=0,
                      optimize=True)
        if buf.tell() <= MAX_GIF_BYTES or count <= 2:
            break
        count //= 2
    with atomic_file(path, "wb") as handle:
        handle.write(buf.getvalue())


def _video_seconds(video: Path, frame_count: int) -> float:
    import av

    with av.open(str(video)) as container:
        stream = container.streams.video[0]
        rate = float(stream.average_rate or 25)
    return frame_count / rate
