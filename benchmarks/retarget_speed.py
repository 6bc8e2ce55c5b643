"""Retargeting speed and keypoint error on the five shared AdaMimic motions (or the bundled sample).

Runs from the repository root with no arguments. frames/s counts source (human) frames through the
whole `retarget()` call (targets, IK, resampling to 50 Hz, floor fix, quality report), wall clock,
with the clips spread over two worker processes (this machine has 2 cores; each clip is solved
sequentially because of the warm start). keypoint_err_mm is the frame-weighted mean of the
per-clip `keypoint_err_mm` (root-relative, against the skeleton scaled to the G1's proportions, see
pipeline/retarget/quality.py). Goal: >= 300 frames/s at <= 10 mm.
"""

from __future__ import annotations

import glob
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
WORKERS = 2


def _clips() -> list[str]:
    shared = sorted(glob.glob(str(ROOT.parent / "shared/data/adamimic_smpl/*.npz")))
    return shared or sorted(glob.glob(str(ROOT / "data/sample/*.npz")))


def _one(args) -> dict:
    path, solver = args
    from pipeline.human.importers import load_human_motion
    from pipeline.retarget import RetargetConfig, retarget

    human = load_human_motion(path)
    started = time.perf_counter()
    _, report = retarget(human, replace(RetargetConfig(), solver=solver), progress=False)
    report["wall_s"] = time.perf_counter() - started
    return report


def _warm(_):
    from pipeline.retarget.core import _robot

    _robot()
    import mink  # noqa: F401
    return os.getpid()


def run(solver: str, clips: list[str]) -> tuple[float, float, list[dict]]:
    with ProcessPoolExecutor(WORKERS) as pool:
        list(pool.map(_warm, range(WORKERS)))  # model build and imports are not retargeting
        started = time.perf_counter()
        reports = list(pool.map(_one, [(c, solver) for c in clips]))
        wall = time.perf_counter() - started
    frames = sum(r["frames_in"] for r in reports)
    err = sum(r["keypoint_err_mm"] * r["frames_in"] for r in reports) / frames
    return frames / wall, err, reports


def main() -> None:
    clips = _clips()
    if not clips:
        raise SystemExit("no clips: neither ../shared/data/adamimic_smpl/*.npz nor data/sample/*.npz")
    print(f"{len(clips)} clips, {WORKERS} worker processes")
    fps, err, reports = run("mink", clips)
    for r in reports:
        print(f"  mink  {r['name']:16s} {r['frames_in']:4d} frames  {r['frames_in'] / r['wall_s']:7.1f} frames/s/proc"
              f"  kp {r['keypoint_err_mm']:5.1f} mm  skate {r['foot_skate_mm_per_frame']:.2f} mm/frame"
              f"  pen {r['max_penetration_mm']:.1f} mm  limit violations {r['joint_limit_violations']}")
    try:
        placo_fps, placo_err, _ = run("placo", clips)
        placo_line = f"placo: {placo_fps:.0f} frames/s, keypoint error {placo_err:.1f} mm"
    except Exception as exc:  # noqa: BLE001 - the alternative solver is reported, not required
        placo_line = f"placo: unavailable ({type(exc).__name__}: {exc})"
    print(f"mink:  {fps:.0f} frames/s, keypoint error {err:.1f} mm (goal >= 300 frames/s, <= 10 mm)")
    print(placo_line)
    print(f"frames_per_s={fps:.0f} keypoint_err_mm={err:.1f}")


if __name__ == "__main__":
    main()
