"""SMPL(-X) body skeleton forward kinematics, without the licensed body-model files.

Skeleton: the 22 body joints of SMPL / SMPL-X (same names, order and tree: `SMPL_PARENTS`).

Rest joint locations (`NEUTRAL_REST_JOINTS`): the neutral, mean-shape (betas = 0) SMPL-X body in
its own frame (y up, x to the body's left, z to the body's front, metres, T-pose). The numbers
were written here from the SMPL-X neutral joint template as baked into the Apache-2.0
`mannequin-x==0.3.0` package (`mannequin/assets/smplx_calibration.npz`, `joint_rest`), rounded to
0.1 mm; the same template is what the SMPL-X joint regressor gives on the neutral mesh.
`tests/test_human_smpl.py` checks the table against the package.

Body shape (betas): we use a *linear joint model*, J(betas) = J_rest + D @ betas, with the
SMPL-X joint shape directions D that `mannequin-x` ships (`joint_dirs`, derived from SMPL-X's
joint regressor and shape blend shapes). It is exact for joint locations (SMPL-X joints are linear
in betas) and needs no licensed file. GVHMR, which made the shared clips, outputs SMPL-X body
parameters, so the SMPL-X template is the right one for them. If the package is absent the
betas fall back to a uniform height scale of the neutral template (`rest_joints(height=...)`).

Standing height: top of the head minus the lowest sole point of the shaped rest body, also a
linear function of betas in the same calibration (1.721 m for the neutral body).

FK convention (SMPL's): joint i's global rotation is R_parent(i) @ R_local(i); the root joint
(pelvis) rotates about its rest location J0, so  pelvis = J0 + trans  and
joint_i = R_root (J_i - J0) + J0 + trans  for a body with all other joints at rest.
"""

from __future__ import annotations

import functools
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.common import quat
from pipeline.human.motion import SMPL_JOINT_NAMES, SMPL_PARENTS

NUM_BODY_JOINTS = 22
NUM_BETAS = 10

# Neutral mean-shape SMPL-X body joints at rest, body frame (x left, y up, z front), metres.
# Source: SMPL-X neutral joint template as shipped in mannequin-x 0.3.0 (Apache-2.0), see above.
NEUTRAL_REST_JOINTS = np.array(
    [
        (0.0031, -0.3514, 0.0120),  # pelvis
        (0.0613, -0.4442, -0.0140),  # left_hip
        (-0.0601, -0.4553, -0.0092),  # right_hip
        (0.0004, -0.2415, -0.0156),  # spine1
        (0.1160, -0.8229, -0.0234),  # left_knee
        (-0.1044, -0.8177, -0.0260),  # right_knee
        (0.0098, -0.1097, -0.0215),  # spine2
        (0.0726, -1.2260, -0.0552),  # left_ankle
        (-0.0889, -1.2284, -0.0462),  # right_ankle
        (-0.0015, -0.0574, 0.0069),  # spine3
        (0.1198, -1.2840, 0.0630),  # left_foot (ball of the foot)
        (-0.1277, -1.2868, 0.0728),  # right_foot
        (-0.0137, 0.1077, -0.0247),  # neck
        (0.0448, 0.0275, -0.0003),  # left_collar
        (-0.0492, 0.0269, -0.0065),  # right_collar
        (0.0111, 0.2682, -0.0040),  # head (joint centre, not the top of the skull)
        (0.1641, 0.0852, -0.0158),  # left_shoulder
        (-0.1518, 0.0804, -0.0191),  # right_shoulder
        (0.4182, 0.0131, -0.0582),  # left_elbow
        (-0.4229, 0.0439, -0.0456),  # right_elbow
        (0.6702, 0.0363, -0.0607),  # left_wrist
        (-0.6722, 0.0394, -0.0609),  # right_wrist
    ],
    dtype=np.float64,
)
# Top of the head and lowest sole point of the neutral rest mesh (y, metres), same source.
NEUTRAL_HEAD_TOP_Y = 0.4193
NEUTRAL_SOLE_Y = -1.3018
NEUTRAL_HEIGHT = NEUTRAL_HEAD_TOP_Y - NEUTRAL_SOLE_Y  # 1.721 m

# In the body frame, the body's up is +y and its front is +z (used to find facing / up axes).
BODY_UP = np.array([0.0, 1.0, 0.0])
BODY_FRONT = np.array([0.0, 0.0, 1.0])
BODY_LEFT = np.array([1.0, 0.0, 0.0])


@dataclass(frozen=True)
class ShapeModel:
    """Linear shape model of the skeleton: joints and height as functions of betas."""

    joint_rest: np.ndarray  # (22, 3)
    joint_dirs: np.ndarray  # (22, 3, B)
    head_top_rest: float
    head_top_dirs: np.ndarray  # (B,)
    sole_rest: np.ndarray  # (S,) y of sole points
    sole_dirs: np.ndarray  # (S, B)
    origin: str

    def joints(self, betas: np.ndarray) -> np.ndarray:
        b = _fit_betas(betas, self.joint_dirs.shape[-1])
        return self.joint_rest + self.joint_dirs @ b

    def height(self, betas: np.ndarray) -> float:
        b = _fit_betas(betas, self.joint_dirs.shape[-1])
        top = self.head_top_rest + self.head_top_dirs @ b
        sole = np.min(self.sole_rest + self.sole_dirs @ b)
        return float(top - sole)


def _fit_betas(betas: np.ndarray, count: int) -> np.ndarray:
    """Uses the first `count` betas (SMPL files carry 10, 16 or 300); pads with zeros."""
    b = np.zeros(count)
    betas = np.asarray(betas, dtype=np.float64).reshape(-1)[:count]
    b[: betas.size] = betas
    return b


def _mannequin_calibration_path() -> Path | None:
    # Locate the data file without importing the package (its __init__ pulls in jaxtyping & co).
    spec = importlib.util.find_spec("mannequin")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "assets" / "smplx_calibration.npz"
    return path if path.is_file() else None


@functools.lru_cache(maxsize=1)
def shape_model() -> ShapeModel | None:
    """The SMPL-X linear joint model from mannequin-x, or None if it is not installed."""
    path = _mannequin_calibration_path()
    if path is None:
        return None
    with np.load(path, allow_pickle=False) as data:
        return ShapeModel(
            joint_rest=data["joint_rest"][:NUM_BODY_JOINTS].astype(np.float64),
            joint_dirs=data["joint_dirs"][:NUM_BODY_JOINTS].astype(np.float64),
            head_top_rest=float(data["head_max_rest"][1]),
            head_top_dirs=data["head_max_dirs"][1].astype(np.float64),
            sole_rest=data["sole_y_rest"].astype(np.float64),
            sole_dirs=data["sole_y_dirs"].astype(np.float64),
            origin=str(path),
        )


def rest_joints(betas: np.ndarray | None = None, height: float | None = None) -> np.ndarray:
    """Rest joint locations (22, 3) in the body frame (y up).

    With betas and mannequin-x installed: the SMPL-X linear joint model. Otherwise (or when
    `height` is given): the neutral template scaled uniformly to that standing height.
    """
    if height is not None:
        return NEUTRAL_REST_JOINTS * (float(height) / NEUTRAL_HEIGHT)
    model = shape_model()
    if model is None or betas is None:
        return NEUTRAL_REST_JOINTS.copy()
    return model.joints(betas)


def standing_height(betas: np.ndarray | None = None) -> float:
    """Standing height (m) of the subject: head top to sole of the shaped rest body."""
    model = shape_model()
    if model is None or betas is None:
        return NEUTRAL_HEIGHT
    return model.height(betas)


def sole_clearance(rest: np.ndarray) -> dict[str, float]:
    """Height (m) of the ankle and foot joints above the sole when standing at rest.

    Scaled from the neutral body by leg length; used to put the soles, not the joints, on the floor.
    """
    scale = (rest[0, 1] - rest[7, 1]) / (NEUTRAL_REST_JOINTS[0, 1] - NEUTRAL_REST_JOINTS[7, 1])
    ankle = 0.5 * (NEUTRAL_REST_JOINTS[7, 1] + NEUTRAL_REST_JOINTS[8, 1]) - NEUTRAL_SOLE_Y
    foot = 0.5 * (NEUTRAL_REST_JOINTS[10, 1] + NEUTRAL_REST_JOINTS[11, 1]) - NEUTRAL_SOLE_Y
    return {"ankle": float(ankle * scale), "foot": float(foot * scale)}


def forward_kinematics(
    local_rotvec: np.ndarray, trans: np.ndarray, rest: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Global joint positions (T, 22, 3) and orientations (T, 22, 4, wxyz).

    local_rotvec (T, 22, 3): SMPL axis-angle, joint 0 = global orientation of the pelvis.
    trans (T, 3): SMPL translation (pelvis = rest[0] + trans when the root is unrotated).
    rest (22, 3): rest joint locations in the same frame as trans.
    """
    local_rotvec = np.asarray(local_rotvec, dtype=np.float64)
    trans = np.asarray(trans, dtype=np.float64)
    num_frames = local_rotvec.shape[0]
    local_q = quat.from_axis_angle(local_rotvec)
    offsets = rest - rest[np.maximum(np.array(SMPL_PARENTS), 0)]
    pos = np.empty((num_frames, NUM_BODY_JOINTS, 3))
    rot = np.empty((num_frames, NUM_BODY_JOINTS, 4))
    rot[:, 0] = local_q[:, 0]
    pos[:, 0] = rest[0] + trans
    for joint in range(1, NUM_BODY_JOINTS):
        parent = SMPL_PARENTS[joint]
        rot[:, joint] = quat.multiply(rot[:, parent], local_q[:, joint])
        pos[:, joint] = pos[:, parent] + quat.rotate(rot[:, parent], offsets[joint])
    return pos, quat.normalize(rot)


# Segment masses as fractions of body mass (de Leva 1996, adult male, rounded) and where each sits:
# halfway between two joints (one joint: at it). Good to a centimetre or two, which is what a
# whole-body centre of mass of a skeleton without a mesh can be.
SEGMENT_MASSES: tuple[tuple[float, tuple[str, ...]], ...] = (
    (0.112, ("pelvis", "left_hip", "right_hip")),  # lower trunk
    (0.163, ("spine1", "spine2")),  # middle trunk
    (0.160, ("spine3", "neck")),  # upper trunk
    (0.069, ("head",)),
    *[(mass, tuple(f"{side}_{joint}" for joint in joints))
      for side in ("left", "right")
      for mass, joints in ((0.142, ("hip", "knee")), (0.043, ("knee", "ankle")), (0.014, ("ankle", "foot")),
                           (0.027, ("shoulder", "elbow")), (0.016, ("elbow", "wrist")), (0.006, ("wrist",)))],
)


def center_of_mass(joint_pos: np.ndarray) -> np.ndarray:
    """Whole-body centre of mass (..., 3) of joint positions (..., 22, 3), from `SEGMENT_MASSES`."""
    index = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
    total = np.zeros(joint_pos.shape[:-2] + (3,))
    for mass, joints in SEGMENT_MASSES:
        total += mass * joint_pos[..., [index[j] for j in joints], :].mean(axis=-2)
    return total / sum(mass for mass, _ in SEGMENT_MASSES)


def angular_momentum(joint_pos: np.ndarray, dt: float) -> np.ndarray:
    """Whole-body angular momentum about the centre of mass, per unit body mass (m^2/s), between
    consecutive frames of joint positions (T, 22, 3): (T - 1, 3). The `SEGMENT_MASSES` segments of two
    joints are thin rods (their own spin counts: a rod is two half masses at ±1/sqrt(12) of its length
    from its middle), the others points."""
    index = {name: i for i, name in enumerate(SMPL_JOINT_NAMES)}
    points, masses = [], []
    for mass, joints in SEGMENT_MASSES:
        ends = joint_pos[..., [index[j] for j in joints], :]
        middle = ends.mean(axis=-2)
        if len(joints) == 2:
            half = (ends[..., 1, :] - ends[..., 0, :]) / (2.0 * np.sqrt(3.0))
            points += [middle - half, middle + half]
            masses += [mass / 2, mass / 2]
        else:
            points.append(middle)
            masses.append(mass)
    points, masses = np.stack(points, axis=-2), np.array(masses) / sum(masses)
    com = (masses[:, None] * points).sum(axis=-2, keepdims=True)
    relative = points - com
    mid = 0.5 * (relative[1:] + relative[:-1])
    velocity = np.diff(relative, axis=0) / dt
    return (masses[:, None] * np.cross(mid, velocity)).sum(axis=-2)


__all__ = [
    "NEUTRAL_REST_JOINTS", "NEUTRAL_HEIGHT", "SEGMENT_MASSES", "SMPL_JOINT_NAMES", "SMPL_PARENTS", "ShapeModel",
    "angular_momentum", "center_of_mass", "forward_kinematics", "rest_joints", "shape_model", "sole_clearance",
    "standing_height",
]
