"""Per-frame MediaPipe Pose landmarks of a video, written to an npz. Runs in `.venv-video`.

    .venv-video/bin/python pipeline/human/video_landmarks.py VIDEO OUT.npz

mediapipe 0.10.21 needs numpy<2 and protobuf<5, which the main environment cannot have, so the
pipeline runs this file as a subprocess with the video venv's interpreter (`make video-venv`).
It imports nothing from `pipeline` on purpose (a different numpy lives here).

The npz holds, for T frames: `world` (T, 33, 3) metric 3D landmarks (MediaPipe's hip-centred
frame: x to the image right, y down, z away from the camera), `image` (T, 33, 3) normalised image
landmarks (x, y in [0, 1] of width/height, z relative depth), `visibility` (T, 33),
`detected` (T,) bool, `fps`, `width`, `height`. Frames without a person are all-zero, detected=False.
Exit codes: 0 written, 3 the video cannot be opened or has no frames.
"""

from __future__ import annotations

import sys

import cv2
import mediapipe as mp
import numpy as np

NUM_LANDMARKS = 33


def extract(video: str, out: str, model_complexity: int = 1) -> int:
    capture = cv2.VideoCapture(video)
    if not capture.isOpened():
        print(f"{video}: cannot open the video", file=sys.stderr)
        return 3
    fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
    width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
    height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
    world, image, visibility, detected = [], [], [], []
    # static_image_mode=False: the tracker follows one person across frames (the first found).
    with mp.solutions.pose.Pose(
        static_image_mode=False, model_complexity=model_complexity, smooth_landmarks=True,
        enable_segmentation=False, min_detection_confidence=0.5, min_tracking_confidence=0.5,
    ) as pose:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            result = pose.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            w = np.zeros((NUM_LANDMARKS, 3), np.float32)
            i = np.zeros((NUM_LANDMARKS, 3), np.float32)
            v = np.zeros(NUM_LANDMARKS, np.float32)
            found = result.pose_world_landmarks is not None and result.pose_landmarks is not None
            if found:
                w[:] = [(p.x, p.y, p.z) for p in result.pose_world_landmarks.landmark]
                i[:] = [(p.x, p.y, p.z) for p in result.pose_landmarks.landmark]
                v[:] = [p.visibility for p in result.pose_landmarks.landmark]
            world.append(w)
            image.append(i)
            visibility.append(v)
            detected.append(found)
    capture.release()
    if not world:
        print(f"{video}: the video has no frames", file=sys.stderr)
        return 3
    np.savez_compressed(
        out, world=np.stack(world), image=np.stack(image), visibility=np.stack(visibility),
        detected=np.array(detected, bool), fps=np.float64(fps), width=np.int64(width), height=np.int64(height),
    )
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
    sys.exit(extract(sys.argv[1], sys.argv[2]))
