"""One control step of an exported policy, shared by `sim2sim` (MuJoCo) and `deploy` (a G1 over DDS).

Both loops measure the robot, hand the measurements to `PolicyStepper.step` and apply its joint
targets; the observation (term list, scales, offsets, oldest-first history), the last action, the
phase with its Δφ^Δ and the odometry's hold between updates live here once, as `policy.json` states
them, so the deployment cannot drift from the loop that reproduces the evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.common.errors import PipelineInputError

METADATA_NAME = "policy.json"
KNOWN_TERMS = {"base_ang_vel", "projected_gravity", "joint_pos", "joint_vel", "last_action", "phase", "psi",
               "odometry"}


def projected_gravity(quat_wxyz) -> np.ndarray:
    """Gravity direction in the base frame, R^T @ (0, 0, -1), for an orientation quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    return -np.array([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])


def yaw_of(quat_wxyz) -> float:
    w, x, y, z = (float(v) for v in quat_wxyz)
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def rotate_z(v: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


class ObservationBuilder:
    """One step's observation from the metadata's term list, and the oldest-first history."""

    def __init__(self, layout: dict, control_rate_hz: float):
        self.terms = layout["terms"]
        self.history = int(layout["history"])
        self.step_dim = int(layout["step_dim"])
        if layout.get("history_order", "oldest_first") != "oldest_first":
            raise PipelineInputError(METADATA_NAME, "observation.history_order",
                                     f"unsupported {layout.get('history_order')!r}")
        for term in self.terms:
            if term["name"] not in KNOWN_TERMS:
                raise PipelineInputError(METADATA_NAME, "observation.terms",
                                         f"term {term['name']!r} is unknown to this deployment loop")
        self.control_rate_hz = control_rate_hz
        self.buffer: np.ndarray | None = None

    def reset(self) -> None:
        self.buffer = None

    def step(self, values: dict[str, np.ndarray]) -> np.ndarray:
        parts = []
        for term in self.terms:
            v = np.asarray(values[term["name"]], dtype=np.float64).reshape(-1)
            if "offset" in term:
                v = v - np.asarray(term["offset"])
            parts.append(v * np.asarray(term.get("scale", 1.0)))
        frame = np.concatenate(parts).astype(np.float32)
        if self.buffer is None:
            self.buffer = np.tile(frame, (self.history, 1))
        else:
            self.buffer = np.concatenate([self.buffer[1:], frame[None]], axis=0)
        return self.buffer.reshape(1, -1)


@dataclass(frozen=True)
class PolicyOutput:
    joint_targets: np.ndarray  # (J,) in the metadata's joint order, radians
    action: np.ndarray  # raw action, next step's last_action
    phase_rate_offset: float  # Δφ^Δ, clamped to the metadata's bounds
    phase: float  # the phase after this step (unclamped, as the env observes it)


class PolicyStepper:
    """The exported policy as a step function: measurements in, joint targets and phase out."""

    def __init__(self, session, meta: dict):
        self.session, self.meta = session, meta
        self.control_dt = float(meta["control_dt"])
        self.phase_rate = float(meta["phase"]["rate"])
        self.offset_bounds = meta["phase"]["offset_bounds"]
        # an episode's step limit: the phase may slow down to 0.25x its rate, so 4 clip lengths cover it
        # (a policy without a phase, the balance policy, has no limit of its own)
        self.max_steps = int(np.ceil(4.0 / self.phase_rate)) if self.phase_rate > 0 else None
        self.num_joints = len(meta["joint_names"])
        self.obs = ObservationBuilder(meta["observation"], 1.0 / self.control_dt)
        self.output_names = [o.name for o in session.get_outputs()]
        self.input_name = session.get_inputs()[0].name
        odometry = [t for t in meta["observation"]["terms"] if t["name"] == "odometry"]
        self.needs_odometry = bool(odometry)
        rate = odometry[0].get("rate_hz") if odometry else None
        # the odometry is sampled every `odometry_period` steps and held in between, as in training
        self.odometry_period = max(1, int(round(1.0 / (self.control_dt * rate)))) if rate else 1
        self.reset()

    def reset(self) -> None:
        self.obs.reset()
        self.phase = 0.0
        self.steps = 0
        self.last_action = np.zeros(self.num_joints)
        self.odometry = np.zeros(3)

    def odometry_due(self) -> bool:
        """True on the steps where a fresh odometry reading is taken (else the last one is held)."""
        return self.steps % self.odometry_period == 0

    def run(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        outs = dict(zip(self.output_names, self.session.run(self.output_names, {self.input_name: obs})))
        return outs["joint_targets"][0], outs["action"][0], float(outs["phase_rate_offset"].reshape(-1)[0])

    def step(self, *, base_ang_vel, projected_gravity, joint_pos, joint_vel, psi: float,
             odometry=None) -> PolicyOutput:
        if odometry is not None and self.odometry_due():
            self.odometry = np.asarray(odometry, dtype=np.float64).reshape(3)
        obs = self.obs.step({
            "base_ang_vel": base_ang_vel, "projected_gravity": projected_gravity, "joint_pos": joint_pos,
            "joint_vel": joint_vel, "last_action": self.last_action, "phase": np.array([self.phase]),
            "psi": np.array([psi]), "odometry": self.odometry,
        })
        joint_targets, action, dphi = self.run(obs)
        dphi = float(np.clip(dphi, *self.offset_bounds))
        self.last_action = action
        self.phase = self.phase + self.phase_rate + dphi
        self.steps += 1
        return PolicyOutput(np.asarray(joint_targets, dtype=np.float64), action, dphi, self.phase)
