"""The tracking env's reference: the clip, its ψ edits and keyframes as per-frame tables.

Computed once at construction, so a step only gathers: the reference's joints, root and bodies per
frame, the zero-action joint targets (feedforward and push prior), the ψ edit at every frame, the
keyframe phases and targets per ψ sample, and where reference-state starts may begin.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs.feedforward import zero_action_targets
from pipeline.envs.own_states import OwnStateRing
from pipeline.envs.start_frames import StartFrameSampler, allowed_start_frames
from pipeline.envs.torch_math import projected_gravity, quat_conjugate, quat_mul, quat_rotate_inverse, yaw_quat
from pipeline.keyframes.tracking_data import TrackingData


class TrackingReference:
    """Mixin of `TrackingEnv`: checks its `TrackingData` and builds the reference tables on it."""

    def _check_data(self, data: TrackingData, source: str) -> None:
        m = data.motion
        if tuple(m.joint_names) != self.robot.joint_names:
            if set(m.joint_names) == set(self.robot.joint_names):
                data.motion = m = m.reorder_joints(self.robot.joint_names)
            else:
                missing = sorted(set(self.robot.joint_names) - set(m.joint_names))
                extra = sorted(set(m.joint_names) - set(self.robot.joint_names))
                raise PipelineInputError(source, "motion.joint_names",
                                         f"do not match the robot (missing {missing}, unexpected {extra})")
        if tuple(m.body_names) != self.robot.tracked_body_names:
            raise PipelineInputError(source, "motion.body_names", "do not match the robot's tracked bodies")
        kf = np.asarray(data.keyframe_frames)
        if kf.ndim != 1 or (kf.size and (kf.min() < 0 or kf.max() >= m.num_frames)) or np.any(np.diff(kf) <= 0):
            raise PipelineInputError(source, "keyframe_frames", f"must be increasing frames in [0, {m.num_frames})")
        if data.num_samples < 1:
            raise PipelineInputError(source, "psi", "needs at least one ψ sample")
        if np.shape(data.keyframe_offsets) != (data.num_samples, kf.size, 3):
            raise PipelineInputError(source, "keyframe_offsets",
                                     f"expected shape ({data.num_samples}, {kf.size}, 3), got {np.shape(data.keyframe_offsets)}")
        if len(data.sparse_scale) != kf.size:
            raise PipelineInputError(source, "sparse_scale", f"expected {kf.size} values")
        if abs(m.fps * self.robot.control_dt - 1.0) > 1e-6:
            raise PipelineInputError(source, "motion.fps", f"must be the control rate {1 / self.robot.control_dt:g}, got {m.fps}")

    def _precompute_reference(self) -> None:
        d, m = self.data, self.data.motion
        t = self.num_frames = m.num_frames
        self.dphi = self.control_dt / m.duration  # Δφ = Δt / T
        self.ref_joint_pos = self._tensor(m.joint_pos)
        self.ref_root_pos = self._tensor(m.root_pos)
        self.ref_root_quat = self._tensor(m.root_quat)
        self.ref_body_pos = self._tensor(m.body_pos)
        self.ref_body_quat = self._tensor(m.body_quat)
        self.ref_qvel = self._tensor(m.qvel())
        targets = zero_action_targets(m, self.cfg.action_offset, self.robot, self.model)
        self.joint_target_table = None if targets is None else self._tensor(targets)  # (T, J)
        prior = getattr(d, "push_prior", None)
        self.push_table = self.push_weight = None
        if prior is not None:  # priors/push_prior.py: a push on top of the feedforward, scaled per sample's ψ
            if self.cfg.action_offset != "feedforward":
                raise PipelineInputError("params.yaml", "env.action_offset",
                                         f"a push prior adds to the feedforward targets, got {self.cfg.action_offset!r}")
            joints = len(self.robot.joint_names)
            if np.shape(prior.joint_offsets) != (t, joints):
                raise PipelineInputError(f"task {d.task}", "push_prior.joint_offsets",
                                         f"shape {np.shape(prior.joint_offsets)}, needs ({t}, {joints})")
            self.push_table = self._tensor(prior.joint_offsets)  # (T, J) at w = 1
            self.push_weight = self._tensor(prior.weight(d.psi))  # (S,)
        self.ref_gravity_xy = projected_gravity(self.ref_root_quat)[:, :2].contiguous()  # for the tilt check
        self.start_heading_quat = yaw_quat(self.ref_root_quat[0])  # (4,): where episodes count odometry from
        root_q = self.ref_root_quat[:, None].expand(-1, m.body_pos.shape[1], -1)
        self.ref_local_pos = quat_rotate_inverse(root_q, self.ref_body_pos - self.ref_root_pos[:, None])
        self.ref_local_quat = quat_mul(quat_conjugate(root_q), self.ref_body_quat)
        samples = np.repeat(np.arange(d.num_samples), t)
        frames = np.tile(np.arange(t), d.num_samples)
        offsets = d.offsets_at_frames(samples, frames).reshape(d.num_samples, t, 3)
        self.offset_table = self._tensor(offsets)  # (S, T, 3): the ψ edit at every frame
        # Velocity of the edit, added to the reference's at reset. D_edit's offsets are piecewise
        # constant (they jump at the keyframes where RSI starts): a finite difference there would be
        # a teleport read as a velocity (−22 m/s at the far-jump landing), so only smooth per-frame
        # offsets (D_rule) have one.
        if d.dense_offsets is not None and t > 1:
            self.offset_vel_table = self._tensor(np.gradient(offsets, m.dt, axis=1))
        else:
            self.offset_vel_table = torch.zeros_like(self.offset_table)
        self.psi = self._tensor(d.psi)
        kf = np.asarray(d.keyframe_frames, dtype=np.int64)
        self.num_keyframes = kf.size
        self.kf_frames = torch.as_tensor(kf, device=self.device)
        # Phase arithmetic in float64: float32 sums drift by ~1e-5 over a long clip, enough to move a
        # keyframe crossing by a step.
        self.kf_phase = self._tensor(kf / (t - 1), torch.float64)
        self.kf_phase_padded = torch.cat([self.kf_phase, torch.full((1,), math.inf, dtype=torch.float64, device=self.device)])
        self.kf_scale = self._tensor(d.sparse_scale)
        self.kf_target_pos = self._tensor(m.body_pos[kf][None] + np.asarray(d.keyframe_offsets)[:, :, None])  # (S,K,B,3)
        self.kf_target_quat = self._tensor(m.body_quat[kf])  # (K,B,4): edits only translate
        allowed = allowed_start_frames(self.cfg.rsi_frames, kf, d.keyframe_labels, t)
        # an episode that ends at the chain's handoff (`end_phase`) never starts at or past it
        allowed = allowed[allowed < round(self.end_phase * (t - 1))] if self.end_phase < 1.0 else allowed
        self.rsi_frame_table = torch.as_tensor(allowed, device=self.device)
        self.start_sampler = StartFrameSampler(self.cfg.rsi_sampling, self.rsi_frame_table, t)
        noise = list(self.cfg.rsi_lin_vel_noise) + list(self.cfg.rsi_ang_vel_noise)
        self.rsi_vel_noise = self._tensor(noise) if self.cfg.rsi_prob > 0 and any(noise) else None
        rot_noise, self.rsi_joint_noise = list(self.cfg.rsi_root_rot_noise), float(self.cfg.rsi_joint_pos_noise)
        self.rsi_rot_noise = self._tensor(rot_noise) if self.cfg.rsi_prob > 0 and any(rot_noise) else None
        self.rsi_pose_noise = self.cfg.rsi_prob > 0 and (self.rsi_rot_noise is not None or self.rsi_joint_noise > 0)
        # An episode that starts at or after the first edited keyframe never meets the edit: the
        # sampler learns nothing about its ψ from it.
        edited = kf[np.asarray(d.edited, dtype=bool)]
        self.first_edit_frame = int(edited[0]) if edited.size else 0
        self.own_states = self.own_state_keyframes = None
        own = self.cfg.own_state_starts
        if own.prob > 0:
            labels = [str(label) for label in d.keyframe_labels] if d.keyframe_labels is not None else []
            marked = [i for i, label in enumerate(labels) if label.startswith(own.at_label)]
            if not marked:
                raise PipelineInputError(f"task {d.task}", "env.own_state_starts.at_label",
                                         f"no keyframe label starts with {own.at_label!r} (labels: {labels})")
            self.own_state_keyframes = torch.as_tensor(marked, device=self.device)
            self.own_states = OwnStateRing(own.capacity, self.device)
