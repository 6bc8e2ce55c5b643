"""Frames to an H.264 mp4 (PyAV; OpenCV's mp4v where PyAV is missing), written atomically."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


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
