"""Pictures of the robot: one renderer (renderer.py) in one look (style.py), the reference as a ghost
(ghost.py), captions (caption.py) and the mp4 writer (mp4.py). Every video the pipeline writes goes through
here: the retarget preview, the keyframes' D_rule video, the evaluation rollouts and `adamimic play`."""
