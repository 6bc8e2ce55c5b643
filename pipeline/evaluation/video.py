"""Offscreen MuJoCo rendering to mp4, with keyframe targets drawn as markers.

Rendering runs headless through the GL that importing `pipeline` chose (`MUJOCO_GL`): EGL where
libEGL is installed (on a machine without a GPU Mesa's llvmpipe serves it: Debian packages libegl1 +
libegl-mesa0 + libgl1-mesa-dri), else OSMesa (libosmesa6). Shadows, reflections, skybox and
multisampling are off: at 640x480 on llvmpipe that is ~20 frames/s instead of ~7. Frames are encoded with PyAV (H.264),
or OpenCV's mp4v when PyAV is unavailable. No torch here: the deployment loop uses it too.
"""

from __future__ import annotations

import os
from pathlib import Path

import mujoco
import numpy as np


MARKER_RGBA_PENDING = np.array([1.0, 0.55, 0.0, 0.8], dtype=np.float32)
MARKER_RGBA_REACHED = np.array([0.1, 0.8, 0.2, 0.8], dtype=np.float32)


class SceneRenderer:
    """A fast offscreen renderer with a camera that follows the pelvis from the side."""

    def __init__(self, model: mujoco.MjModel, width: int = 640, height: int = 480):
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, height)
        model.vis.quality.offsamples = 0
        try:
            self.renderer = mujoco.Renderer(model, height, width)
        except Exception as error:  # EGL unusable here: retry with OSMesa in a fresh process only
            raise RuntimeError(
                f"offscreen rendering failed with MUJOCO_GL={os.environ.get('MUJOCO_GL')} ({error}); "
                "install Mesa EGL (libegl1 libegl-mesa0 libgl1-mesa-dri) or set MUJOCO_GL=osmesa "
                "with libosmesa6") from error
        flags = self.renderer.scene.flags
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                     mujoco.mjtRndFlag.mjRND_SKYBOX, mujoco.mjtRndFlag.mjRND_FOG):
            flags[flag] = 0
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.distance, self.camera.azimuth, self.camera.elevation = 3.5, 90.0, -12.0
        self.model = model

    def render(self, data: mujoco.MjData, markers: np.ndarray | None = None,
               marker_rgba: np.ndarray | None = None, marker_size: float = 0.04) -> np.ndarray:
        """RGB frame (H, W, 3) uint8; `markers` (M, 3) world positions drawn as spheres."""
        self.camera.lookat[:] = [data.qpos[0], data.qpos[1], 0.8]
        self.renderer.update_scene(data, camera=self.camera)
        if markers is not None and len(markers):
            add_markers(self.renderer.scene, markers, marker_rgba, marker_size)
        return self.renderer.render()

    def close(self) -> None:
        self.renderer.close()


def add_markers(scene: mujoco.MjvScene, positions: np.ndarray, rgba: np.ndarray | None = None,
                size: float = 0.04) -> int:
    """Appends spheres to the scene's user geoms (mjv_initGeom); returns how many fit."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    rgba = np.broadcast_to(MARKER_RGBA_PENDING if rgba is None else np.asarray(rgba, np.float32),
                           (len(positions), 4))
    added = 0
    for pos, color in zip(positions, rgba):
        if scene.ngeom >= scene.maxgeom:
            break
        mujoco.mjv_initGeom(scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE,
                            np.array([size, 0.0, 0.0]), pos, np.eye(3).reshape(-1),
                            np.asarray(color, np.float32))
        scene.geoms[scene.ngeom].category = mujoco.mjtCatBit.mjCAT_DECOR
        scene.ngeom += 1
        added += 1
    return added


class Mp4Writer:
    """Streams frames into an mp4 next to `path` and renames it into place on `close()` (atomic:
    the file appears complete or not at all). PyAV H.264, else OpenCV mp4v."""

    def __init__(self, path: str | Path, fps: int, width: int, height: int):
        self.path, self.fps, self.width, self.height = Path(path), int(fps), int(width), int(height)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp.mp4")
        self.count = 0
        try:
            import av

            self._av = av
            self.container = av.open(str(self.tmp), mode="w")
            self.stream = self.container.add_stream("libx264", rate=self.fps)
            self.stream.width, self.stream.height, self.stream.pix_fmt = width, height, "yuv420p"
            self.stream.options = {"crf": "23", "preset": "veryfast"}
            self.cv2_writer = None
        except ImportError:
            import cv2

            self._av = None
            self.cv2_writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))

    def add(self, frame: np.ndarray) -> None:
        frame = np.ascontiguousarray(frame[..., :3])
        if self._av is not None:
            for packet in self.stream.encode(self._av.VideoFrame.from_ndarray(frame, format="rgb24")):
                self.container.mux(packet)
        else:
            self.cv2_writer.write(frame[..., ::-1])
        self.count += 1

    def close(self) -> Path:
        try:
            if self._av is not None:
                for packet in self.stream.encode():
                    self.container.mux(packet)
                self.container.close()
            else:
                self.cv2_writer.release()
            os.replace(self.tmp, self.path)
        finally:
            if self.tmp.exists():
                self.tmp.unlink()
        return self.path
