"""`load_human_motion(path)`: a human clip from a file, as a `HumanMotion` in the pipeline frame.

Dispatch on the file:
  * `.npz`: AMASS-style SMPL/SMPL-H/SMPL-X parameters: `poses` (T, 66|72|156|165) axis-angle
    (the first 22 joints are the body), `trans` (T, 3), `betas` (B,), `mocap_framerate` (or `fps`),
    optional `gender` (ignored: one neutral skeleton). The up axis is found from the data (AMASS
    is z-up; the shared GVHMR-made clips turned out to be z-up as well, starting facing +y).
  * `.pt`: GVHMR `hmr4d_results.pt`, `smpl_params_global` with `global_orient` (L, 3),
    `body_pose` (L, 63), `betas` (L, 10), `transl` (L, 3): SMPL-X body, gravity along -y, 30 fps.
  * video (`.mp4 .avi .mov .mkv .webm`): `pipeline.human.video` (mediapipe in its own venv).
Frame conversion to z-up / floor at 0 / facing +x: `pipeline.human.frames`.
Bad input raises `PipelineInputError(file, field, problem)`.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from pipeline.common.errors import PipelineInputError
from pipeline.human.frames import human_motion_from_smpl
from pipeline.human.motion import HumanMotion

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")
NPZ_POSE_WIDTHS = (66, 72, 156, 165)  # SMPL body only, SMPL, SMPL-H, SMPL-X
GVHMR_FPS = 30.0


def load_human_motion(path: str | Path) -> HumanMotion:
    path = Path(path)
    if not path.is_file():
        raise PipelineInputError(path, None, "file not found")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return load_amass_npz(path)
    if suffix == ".pt":
        return load_gvhmr_pt(path)
    if suffix in VIDEO_SUFFIXES:
        from pipeline.human.video import load_video

        return load_video(path)
    raise PipelineInputError(path, None, f"unknown file type {suffix!r}: expected .npz, .pt or a video")


def _scalar(value, source: Path, field: str) -> float:
    arr = np.asarray(value)
    if arr.size != 1 or arr.dtype.kind not in "iuf":
        raise PipelineInputError(source, field, f"expected one number, got {arr.dtype} shape {arr.shape}")
    return float(arr.reshape(()))


def load_amass_npz(path: str | Path) -> HumanMotion:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise PipelineInputError(path, None, f"cannot read as npz: {exc}") from None
    for key in ("poses", "trans", "betas"):
        if key not in arrays:
            raise PipelineInputError(path, key, f"missing (file has {sorted(arrays)})")
    fps_key = next((k for k in ("mocap_framerate", "mocap_frame_rate", "fps") if k in arrays), None)
    if fps_key is None:
        raise PipelineInputError(path, "mocap_framerate", f"missing (file has {sorted(arrays)})")
    fps = _scalar(arrays[fps_key], path, fps_key)
    poses = arrays["poses"]
    if poses.ndim != 2 or poses.shape[1] not in NPZ_POSE_WIDTHS or poses.dtype.kind not in "iuf":
        raise PipelineInputError(
            path, "poses", f"expected shape (T, 66|72|156|165) numbers, got {poses.dtype} {poses.shape}"
        )
    trans, betas = arrays["trans"], arrays["betas"]
    for key, arr in (("trans", trans), ("betas", betas)):
        if arr.dtype.kind not in "iuf":
            raise PipelineInputError(path, key, f"expected numbers, got {arr.dtype}")
    if betas.ndim == 2:  # some exporters store per-frame betas: the subject is one person
        betas = betas.mean(axis=0)
    local_rotvec = poses[:, :66].reshape(-1, 22, 3)
    return human_motion_from_smpl(
        local_rotvec=local_rotvec, trans=trans, betas=betas, fps=fps, source=str(path), name=path.stem
    )


def load_gvhmr_pt(path: str | Path) -> HumanMotion:
    path = Path(path)
    import torch

    try:
        results = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types (pickle, zip, runtime) for a bad file
        raise PipelineInputError(path, None, f"cannot read as a torch file: {exc}") from None
    if not isinstance(results, dict) or "smpl_params_global" not in results:
        raise PipelineInputError(path, "smpl_params_global", "missing: not a GVHMR hmr4d_results.pt")
    params = results["smpl_params_global"]
    arrays = {}
    for key, width in (("global_orient", 3), ("body_pose", 63), ("betas", None), ("transl", 3)):
        field = f"smpl_params_global.{key}"
        if not isinstance(params, dict) or key not in params:
            raise PipelineInputError(path, field, "missing")
        value = params[key]
        arr = value.detach().cpu().double().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
        if arr.ndim != 2 or (width is not None and arr.shape[1] != width) or arr.dtype.kind not in "iuf":
            want = f"(L, {width})" if width else "(L, B)"
            raise PipelineInputError(path, field, f"expected shape {want}, got {arr.dtype} {arr.shape}")
        arrays[key] = arr.astype(np.float64)
    frames = arrays["global_orient"].shape[0]
    if arrays["body_pose"].shape[0] != frames:
        raise PipelineInputError(path, "smpl_params_global.body_pose", f"has {arrays['body_pose'].shape[0]} frames, global_orient {frames}")
    local_rotvec = np.concatenate([arrays["global_orient"], arrays["body_pose"]], axis=1).reshape(-1, 22, 3)
    betas = arrays["betas"].mean(axis=0)  # one subject; GVHMR repeats them per frame
    name = path.parent.name if path.stem == "hmr4d_results" else path.stem
    # GVHMR's global frame has gravity along -y: up is +y, known from the format.
    return human_motion_from_smpl(
        local_rotvec=local_rotvec, trans=arrays["transl"], betas=betas, fps=GVHMR_FPS,
        source=str(path), name=name, up_axis="+y",
    )
