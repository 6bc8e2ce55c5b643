"""The vectorised G1 tracking environment of AdaMimic (paper "Background" and appendix).

Everything per step is batched torch over N worlds; reference quantities are precomputed per
frame (and keyframe targets per ψ-sample and keyframe) at construction so a step only gathers.
Physics sits behind `pipeline.sim` (`PhysicsBackend`); this file never touches MjData.

Phase φ ∈ [0, 1] maps to reference frame round(φ (T−1)). A step advances φ by Δφ = Δt/T, plus
stage 2's offset clamped to [−0.75Δφ, +Δφ]; it "crosses" keyframe k when φ_prev < φ_k <= φ_new,
and only then pays the sparse group (against the keyframe's target for the episode's ψ sample).
Episodes auto-reset: the returned observation of a finished world is its new episode's first;
the last observation of the finished episode is in info["final_obs"].
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs import rewards as R
from pipeline.envs.config import EnvConfig
from pipeline.envs.feedforward import zero_action_targets
from pipeline.envs.own_states import FIELDS as OWN_STATE_FIELDS
from pipeline.envs.own_states import OwnStateRing
from pipeline.envs.randomization import DomainRandomizer
from pipeline.envs.sampling import SampleSampler
from pipeline.envs.scene import build_scene, make_physics, terrain_fields_per_sample
from pipeline.envs.start_frames import StartFrameSampler, allowed_start_frames
from pipeline.envs.torch_math import (
    projected_gravity,
    quat_conjugate,
    quat_from_rotvec,
    quat_mul,
    quat_rotate_inverse,
    yaw_quat,
)
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.robot.g1 import joint_limits, load_robot_config

FRAME_OBS_DIM = 3 + 3 + 27 + 27 + 27 + 1 + 1 + 3  # per history step (for the 27-joint G1)
# The dense group's terms in the order `_score` stacks them (the global ones only in dense tracking).
_DENSE_TERMS = ("local_body_pos", "local_body_rot", "local_joint_pos", "root_tilt", "root_ang_vel", "feet_orientation",
                "joint_acc", "joint_vel", "action_rate", "smoothness", "torques", "torque_limits", "joint_pos_limits",
                "joint_vel_limits")
_GLOBAL_TERMS = ("global_body_pos", "global_body_rot", "global_feet_pos")
_EPS = 1e-6


class TrackingEnv:
    def __init__(self, cfg: EnvConfig, data: TrackingData, *, num_envs: int, backend="cpu", device="cpu",
                 seed: int = 0, task=None):
        self.cfg = cfg
        self.data = data
        self.robot = load_robot_config()
        self.device = torch.device(device)
        source = f"task {data.task}"
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs <= 0:
            raise PipelineInputError(source, "num_envs", f"must be a positive integer, got {num_envs!r}")
        self.num_envs = n = int(num_envs)
        self._check_data(data, source)

        model, terrain_layout = build_scene(data, task, source, cfg.physics)
        self.backend = make_physics(backend, model, n, cfg.physics_threads, device, source)
        self.model = self.backend.model  # the compiled scene with the backend's sensors
        self.decimation = int(self.backend.decimation)
        self.control_dt = self.robot.control_dt
        self.sim_dt = self.control_dt / self.decimation

        # All randomness comes from torch's global RNG (seeded by the caller): a trainer that saves
        # and restores it replays the same episodes after a resume. `seed` stays for the contract.
        self.seed = seed
        self._precompute_reference()
        self._precompute_robot()
        self.randomizer = DomainRandomizer(cfg.randomization, self.model, self.backend)
        self.sampler = SampleSampler(cfg.sampling, data.psi, data.psi_raw, n, self.device)
        self._terrain_fields = terrain_fields_per_sample(self.model, terrain_layout, data.psi, source)

        self.actor_obs_dim = FRAME_OBS_DIM * cfg.observations.history
        self.critic_obs_dim = self.actor_obs_dim + 3 + self.num_joints + 1 + 1
        self.action_dim = self.num_joints

        self.termination_threshold = float(cfg.terminations.keyframe_error.start)
        self.penalty_scale = 1.0  # the paper's weights until a trainer's curriculum says otherwise
        # The per-step tensor work, compiled into a few fused kernels when asked (`env.compile`): on a
        # GPU the eager step is ~450 small launches whose host time, not the worlds, sets its speed.
        self._score_fn, self._observe_fn = self._score, self._observe
        if cfg.compile:
            self._score_fn = torch.compile(self._score, fullgraph=True, dynamic=False)
            self._observe_fn = torch.compile(self._observe, fullgraph=True, dynamic=False)
        self.penalty_curriculum_started = False
        # episodes finished / terminated since the last curriculum update (the penalty curriculum's input),
        # kept as device tensors so counting them costs no host sync per step
        self._clear_episode_counts()
        self._alloc_state()

    # ------------------------------------------------------------------------------------ set-up
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

    def _tensor(self, x, dtype=torch.float32):
        return torch.as_tensor(np.array(x), dtype=dtype, device=self.device)  # a copy: dataset arrays are read-only

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
        self.rsi_frame_table = torch.as_tensor(allowed_start_frames(self.cfg.rsi_frames, kf, d.keyframe_labels, t),
                                               device=self.device)
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

    def _precompute_robot(self) -> None:
        cfg, rc = self.cfg.rewards, self.robot
        self.num_joints = rc.num_joints
        # Steps read joints as the contiguous qpos[7:] / qvel[6:] slices (no gather): check the layout.
        qadr = [self.model.jnt_qposadr[self.model.joint(n).id] for n in rc.joint_names]
        if qadr != list(range(7, 7 + rc.num_joints)) or self.model.nq != 7 + rc.num_joints:
            raise PipelineInputError("robot", "joints", "the model's qpos is not free joint + the 27 joints in action order")
        names = rc.tracked_body_names
        for key, group in (("rewards.lower_body", cfg.lower_body), ("rewards.feet", cfg.feet)):
            unknown = [b for b in group if b not in names]
            if unknown:
                raise PipelineInputError("env", key, f"unknown tracked bodies {unknown}")
        s = cfg.sigma2
        inv = [1.0 / (s.lower_body_pos if b in cfg.lower_body else s.upper_body_pos) for b in names]
        self.inv_sigma2_pos = self._tensor(inv)
        self.feet_idx = torch.as_tensor([names.index(f) for f in cfg.feet], device=self.device)
        self.default_joint_pos = self._tensor(rc.default_joint_pos)
        self.action_scale = self._tensor(rc.action_scale)
        lim = joint_limits(self.model, rc.joint_names)
        self.joint_pos_low, self.joint_pos_high = self._tensor(lim[:, 0]), self._tensor(lim[:, 1])
        lo, hi = R.soft_range(lim[:, 0], lim[:, 1], cfg.soft_joint_pos_limit)
        self.soft_pos_low, self.soft_pos_high = self._tensor(lo), self._tensor(hi)
        self.soft_vel_limit = self._tensor(rc.velocity_limit * cfg.soft_joint_vel_limit)
        self.soft_torque_limit = self._tensor(rc.effort_limit * cfg.soft_torque_limit)
        term = self.cfg.terminations
        self.height_termination = term.base_height_enabled and self.data.task not in term.base_height_exempt_tasks
        self.odom_every = max(1, int(round(1.0 / (self.cfg.observations.odometry_rate_hz * self.control_dt))))

    def _alloc_state(self) -> None:
        n, j, dev = self.num_envs, self.num_joints, self.device
        z = lambda *shape: torch.zeros(*shape, device=dev)  # noqa: E731
        self.phase = torch.zeros(n, dtype=torch.float64, device=dev)
        self.frame = torch.zeros(n, dtype=torch.long, device=dev)
        self.sample = torch.zeros(n, dtype=torch.long, device=dev)
        self.next_kf = torch.zeros(n, dtype=torch.long, device=dev)
        self.episode_step = torch.zeros(n, dtype=torch.long, device=dev)
        self.start_frame = torch.zeros(n, dtype=torch.long, device=dev)
        # the episode crossed a keyframe with a body-mean error over the success test's threshold
        self.keyframe_missed = torch.zeros(n, dtype=torch.bool, device=dev)
        self.prev_action, self.prev_action2 = z(n, j), z(n, j)
        self.prev_joint_vel = z(n, j)
        self.odometry, self.odom_origin = z(n, 3), z(n, 3)
        self.odom_origin_quat = torch.zeros(n, 4, device=dev)
        self.odom_origin_quat[:, 0] = 1.0
        self.obs_history = z(n, self.cfg.observations.history, FRAME_OBS_DIM)
        self.privileged = z(n, self.critic_obs_dim - self.actor_obs_dim)
        self.arange = torch.arange(n, device=dev)
        # Control delay: ring buffer of joint targets; lag[i, s] = control steps back used at substep s.
        max_delay = int(round(self.randomizer.max_delay_s / self.sim_dt))
        self.target_slots = max_delay // self.decimation + 2
        self.target_history = z(self.target_slots, n, j)
        self.target_ptr = 0
        self.delay_lag = torch.zeros(n, self.decimation, dtype=torch.long, device=dev)
        self.delay_substeps = torch.zeros(n, dtype=torch.long, device=dev)
        self.push_timer = z(n)

    # ------------------------------------------------------------------------------------ API
    def reset(self) -> dict[str, torch.Tensor]:
        with self._torch_threads():
            self._reset_worlds(self.arange)
            return self._obs_dict()

    @contextlib.contextmanager
    def _torch_threads(self):
        """Runs the env's torch work on `cfg.torch_threads` threads and restores the caller's count.
        Per-step tensors are small; torch's OpenMP workers beside the physics threads on 2 cores
        cost ~40 % of the env's throughput (benchmarks/env_throughput.py), and a scoped switch
        (sub-microsecond) leaves the trainer's own setting alone."""
        wanted = self.cfg.torch_threads
        if wanted <= 0 or self.device.type != "cpu":
            yield
            return
        previous = torch.get_num_threads()
        if previous != wanted:
            torch.set_num_threads(wanted)
        try:
            yield
        finally:
            if previous != wanted:
                torch.set_num_threads(previous)

    def obs_layout(self) -> dict:
        """Where each quantity sits in one history step of the actor observation (oldest step first,
        newest last) and in the critic's privileged tail, as [start, stop) pairs."""
        j = self.num_joints
        names = [("base_ang_vel", 3), ("projected_gravity", 3), ("joint_pos_rel", j), ("joint_vel", j),
                 ("prev_action", j), ("phase", 1), ("psi", 1), ("odometry", 3)]
        priv = [("base_lin_vel", 3), ("ref_joint_pos", j), ("base_height", 1), ("phase_to_next_keyframe", 1)]

        def spans(items, start=0):
            out = {}
            for name, size in items:
                out[name] = [start, start + size]
                start += size
            return out

        return {"history": self.cfg.observations.history, "frame_dim": FRAME_OBS_DIM,
                "actor_frame": spans(names), "critic_privileged": spans(priv, self.actor_obs_dim)}

    def pinned_observation_stats(self) -> list[tuple[list[int], float, float]]:
        """[(actor columns, mean, variance)] the networks' normalisers hold fixed instead of
        tracking (observations.psi_scale); the critic's observation starts with the actor's, so the
        same columns serve both."""
        if self.cfg.observations.psi_scale != "samples":
            return []
        start = self.obs_layout()["actor_frame"]["psi"][0]
        columns = [h * FRAME_OBS_DIM + start for h in range(self.cfg.observations.history)]
        psi = self.psi.double()
        return [(columns, float(psi.mean()), float(psi.var(unbiased=False)))]

    def set_termination_threshold(self, value: float) -> float:
        c = self.cfg.terminations.keyframe_error
        self.termination_threshold = float(min(max(value, c.min), c.max))
        return self.termination_threshold

    @property
    def termination_threshold(self) -> float:
        """The keyframe-error termination threshold (m) the curriculum sets; inf: falls only."""
        return self._termination_threshold

    @termination_threshold.setter
    def termination_threshold(self, value: float) -> None:
        self._termination_threshold = value = float(value)
        # The step compares against a device tensor made once per change: a Python float would be a
        # copy to the device every step, and a constant that a compiled step recompiles for.
        squared = self.cfg.terminations.keyframe_error.measure == "max"
        self._threshold_tensor = torch.tensor(value * value if squared else value, device=self.device)

    @property
    def penalty_scale(self) -> float:
        """Factor on the dense penalties' weights (the penalty curriculum's; 1: the paper's weights)."""
        return self._penalty_scale

    @penalty_scale.setter
    def penalty_scale(self, value: float) -> None:
        self._penalty_scale = value = float(value)
        w, dt = self.cfg.rewards.weights, self.control_dt if self.cfg.rewards.scale_by_dt else 1.0
        names = list(_DENSE_TERMS) + (list(_GLOBAL_TERMS) if self.cfg.variant.tracking == "dense" else [])
        weights = [getattr(w, name) * (value if getattr(w, name) < 0 else 1.0) * dt for name in names]
        self._dense_weights = torch.tensor(weights, device=self.device)

    def _keyframe_error_exceeded(self, err2: torch.Tensor) -> torch.Tensor:
        """(N, bodies) squared position errors -> (N,) past the keyframe-error termination threshold."""
        if self.cfg.terminations.keyframe_error.measure == "mean":
            return err2.sqrt().mean(-1) > self._threshold_tensor
        return err2.max(-1).values > self._threshold_tensor

    def update_curriculum(self, progress: float) -> float:
        """Called once per training iteration. Sets the keyframe-error termination threshold
        (returned) from training progress p ∈ [0, 1], and the dense penalty scale (`penalty_scale`)
        from the share of episodes that fell since the last call (see `PenaltyCurriculum`)."""
        pc = self.cfg.rewards.penalty_curriculum
        if pc.enabled:
            if not self.penalty_curriculum_started:
                self.penalty_scale, self.penalty_curriculum_started = pc.initial, True
            elif int(self.episodes_finished) > 0:
                fall_rate = int(self.episodes_terminated) / int(self.episodes_finished)
                self.penalty_scale = pc.next_scale(self.penalty_scale, fall_rate)
        self._clear_episode_counts()
        return self.set_termination_threshold(self.cfg.terminations.keyframe_error.threshold_at(progress))

    def _clear_episode_counts(self) -> None:
        self.episodes_finished = torch.zeros((), dtype=torch.long, device=self.device)
        self.episodes_terminated = torch.zeros((), dtype=torch.long, device=self.device)

    def _action_offset(self, frame: torch.Tensor) -> torch.Tensor:
        """Joint targets at a zero action: the default pose, or the reference's joints at `frame`
        (with the feedforward of envs/feedforward.py for "feedforward", and the push prior's w(ψ) · push
        of the sample each world tracks when the data has one)."""
        if self.cfg.action_offset == "default":
            return self.default_joint_pos
        if self.push_table is None:
            return self.joint_target_table[frame]
        return self.joint_target_table[frame] + self.push_weight[self.sample][:, None] * self.push_table[frame]

    def step(self, action: torch.Tensor, phase_rate_offset: torch.Tensor | None = None):
        """One control step of every world; see the module docstring and docs/INTERFACES.md."""
        with self._torch_threads():
            return self._step(action, phase_rate_offset)

    def _step(self, action: torch.Tensor, phase_rate_offset: torch.Tensor | None):
        cfg = self.cfg
        action = action.to(self.device, torch.float32).clamp(-cfg.action_clip, cfg.action_clip)

        # ---- phase (first: the reference action offset aims at the frame this step ends on)
        dphi = self.dphi
        if phase_rate_offset is not None:
            off = phase_rate_offset.to(self.device, torch.float64).reshape(-1)
            dphi = dphi + off.clamp(-0.75 * self.dphi, self.dphi)
        self.phase = phase = self.phase + dphi
        self.frame = frame = (phase * (self.num_frames - 1)).round().long().clamp_(0, self.num_frames - 1)
        self.episode_step += 1

        target = self._action_offset(frame) + self.action_scale * action
        self._apply_pushes()
        self.backend.step(self._delayed_control(target))

        odometry_noise = self._odometry_noise(self.num_envs)  # drawn outside `_observe`, which may be compiled
        b = self.backend
        s = self._score_fn(b.qpos, b.qvel, b.site_pos, b.site_quat, b.actuator_force, b.foot_contact, action)
        terminated, truncated, crossed = s["terminated"], s["truncated"], s["crossed"]
        self.next_kf = s["next_kf"]
        missed = crossed & (s["keyframe_error_w"].mean(-1) > self.cfg.sampling.success_threshold_m)
        self.keyframe_missed = self.keyframe_missed | missed
        self.prev_action2, self.prev_action = self.prev_action, action
        self.prev_joint_vel = s["joint_vel"]
        self.obs_history, self.privileged, self.odometry = self._observe_fn(s["gravity"], odometry_noise)
        final_obs = self._obs_dict()  # pre-reset: the finished episodes' last observations
        done = terminated | truncated
        if self.own_states is not None:
            self._record_own_states(crossed & ~done, s["crossed_kf"])
        info = {
            "keyframe_crossed": crossed,
            "keyframe_index": s["crossed_kf"],
            "body_pos_error_w": s["error_w"],
            "keyframe_body_error_w": s["keyframe_error_w"],
            "keyframe_miss_w": s["keyframe_miss_w"],
            "body_pos_error_local": s["local_error"],
            "joint_acc": s["joint_acc"],
            "phase": phase.to(torch.float32),
            "frame": frame.clone(),
            "joint_pos": s["joint_pos"],
            "psi": self.psi[self.sample],
            "sample": self.sample.clone(),
            "terms": s["terms"],
            "final_obs": final_obs,
            "termination_threshold": self.termination_threshold,
            # which checks fired (several may on one step): diagnostics for the trainer's log
            "terminated_by": {"keyframe_error": s["by_keyframe"], "tilt": s["by_tilt"], "base_height": s["by_height"]},
            "tilt_error_xy": s["tilt_error_xy"],  # which way a fall went (evaluation's endings)
        }
        sparse, dense = s["sparse"], s["dense"]
        self.episodes_finished = self.episodes_finished + done.sum()
        self.episodes_terminated = self.episodes_terminated + terminated.sum()
        if bool(done.any()):
            ended = done.nonzero().squeeze(-1)
            self._record_psi_outcomes(ended, s)
            self.start_sampler.record(self.start_frame[ended], terminated[ended])
            self._reset_worlds(ended)
        return self._obs_dict(), {"sparse": sparse, "dense": dense}, terminated, truncated, info

    def _record_own_states(self, alive_crossing: torch.Tensor, crossed_kf: torch.Tensor) -> None:
        """Copies into the ring the worlds that crossed an `own_state_starts` keyframe this step and are
        still up, if their episode started before that keyframe (a reference-state start there would
        only copy the reference)."""
        crossed_frame = self.kf_frames[crossed_kf.clamp(min=0)]
        keep = alive_crossing & torch.isin(crossed_kf, self.own_state_keyframes) & (self.start_frame < crossed_frame)
        ids = keep.nonzero().squeeze(-1)
        if ids.numel() == 0:
            return
        state = {"qpos": self.backend.qpos[ids], "qvel": self.backend.qvel[ids]}
        state.update({name: getattr(self, name)[ids] for name in OWN_STATE_FIELDS if name not in state})
        self.own_states.add(state)

    def _record_psi_outcomes(self, ended: torch.Tensor, s: dict) -> None:
        """Tells the ψ sampler how the episodes that met the edit ended (`SamplingConfig.judge`)."""
        tested = ended[self.start_frame[ended] < self.first_edit_frame]
        if self.cfg.sampling.judge == "termination":
            self.sampler.record(tested, self.sample[tested], s["terminated"][tested])
            return
        failed = s["by_tilt"][tested] | s["by_height"][tested] | self.keyframe_missed[tested]
        judged = failed | s["truncated"][tested]
        self.sampler.record(tested[judged], self.sample[tested[judged]], failed[judged])

    def _score(self, qpos, qvel, site_pos, site_quat, torque, foot_contact, action):
        """Rewards and terminations of every world after the physics step, as one pure tensor function
        of the state: no host sync and no data-dependent shapes (the worlds that cross a keyframe are
        selected by masks, not indices), so a step costs the same launches whatever happens in it and
        `env.compile` can fuse it whole."""
        cfg, w = self.cfg, self.cfg.rewards.weights
        phase, frame, sample = self.phase, self.frame, self.sample
        root_pos, root_quat = qpos[:, 0:3], qpos[:, 3:7]
        gravity = projected_gravity(root_quat)  # the root tilt term, the tilt check and the observations
        joint_pos, joint_vel = qpos[:, 7:], qvel[:, 6:]

        # ---- dense group
        root_q = root_quat[:, None].expand_as(site_quat)
        local_pos = quat_rotate_inverse(root_q, site_pos - root_pos[:, None])
        local_err2 = ((local_pos - self.ref_local_pos[frame]) ** 2).sum(-1)
        local_quat = quat_mul(quat_conjugate(root_q), site_quat)
        s2 = cfg.rewards.sigma2
        joint_acc = (joint_vel - self.prev_joint_vel) / self.control_dt
        terms = {
            "local_body_pos": torch.exp(-(local_err2 * self.inv_sigma2_pos).mean(-1)),
            "local_body_rot": R.rotation_kernel(local_quat, self.ref_local_quat[frame], s2.body_rot),
            "local_joint_pos": R.joint_kernel(joint_pos, self.ref_joint_pos[frame], s2.joint_pos),
            "root_tilt": R.vector_kernel(gravity[:, :2], self.ref_gravity_xy[frame], s2.root_tilt),
            "root_ang_vel": R.vector_kernel(qvel[:, 3:6], self.ref_qvel[frame, 3:6], s2.root_ang_vel),
            "feet_orientation": R.feet_orientation(site_quat[:, self.feet_idx], foot_contact.to(torch.float32)),
            "joint_acc": R.sum_sq(joint_acc),
            "joint_vel": R.sum_sq(joint_vel),
            "action_rate": R.sum_sq(action - self.prev_action),
            "smoothness": R.smoothness(action, self.prev_action, self.prev_action2),
            "torques": R.sum_sq(torque),
            "torque_limits": R.over_limit(torque, self.soft_torque_limit),
            "joint_pos_limits": R.outside_range(joint_pos, self.soft_pos_low, self.soft_pos_high),
            "joint_vel_limits": R.over_limit(joint_vel, self.soft_vel_limit),
        }
        dense_terms = [terms[name] for name in _DENSE_TERMS]

        # ---- global errors against the (edited) reference at the current frame: info + dense variant
        ref_pos_w = self.ref_body_pos[frame] + self.offset_table[sample, frame][:, None]
        err2_w = ((site_pos - ref_pos_w) ** 2).sum(-1)
        error_w = err2_w.sqrt()
        terminated = torch.zeros_like(phase, dtype=torch.bool)
        if cfg.variant.tracking == "dense":
            dense_terms += self._global_terms(err2_w, site_quat, self.ref_body_quat[frame])
            terminated = self._keyframe_error_exceeded(err2_w)
        # the weights carry the penalty curriculum and the control step (see `penalty_scale`)
        dense = (torch.stack(dense_terms, -1) * self._dense_weights).sum(-1)

        # ---- sparse group: paid by the worlds crossing a keyframe this step, against its target
        crossed = phase >= self.kf_phase_padded[self.next_kf] - _EPS
        k = (torch.searchsorted(self.kf_phase, phase + _EPS, right=True) - 1).clamp(min=0)
        miss = site_pos - self.kf_target_pos[sample, k]
        err2 = (miss**2).sum(-1)
        keyframe_error_w = torch.where(crossed[:, None], err2.sqrt(), error_w)
        keyframe_miss_w = torch.where(crossed[:, None], miss.mean(1), 0.0)
        sparse = torch.zeros_like(error_w[:, 0])
        if cfg.variant.tracking == "sparse":
            g = self._global_terms(err2, site_quat, self.kf_target_quat[k])
            paid = self.kf_scale[k] * (w.global_body_pos * g[0] + w.global_body_rot * g[1] + w.global_feet_pos * g[2])
            sparse = torch.where(crossed, paid, 0.0)
            terminated = crossed & self._keyframe_error_exceeded(err2)
        by_keyframe = terminated

        # ---- terminations
        tc = cfg.terminations
        tilt_error_xy = gravity[:, :2] - self.ref_gravity_xy[frame]  # + x: leaning further forward than the reference
        tilt_xy = tilt_error_xy if tc.relative_to_reference else gravity[:, :2]
        by_tilt = (tilt_xy**2).sum(-1) > tc.max_tilt**2
        by_height = torch.zeros_like(by_tilt)
        if self.height_termination:
            min_height = torch.full_like(root_pos[:, 2], tc.min_base_height)
            if tc.relative_to_reference:
                ref_z = self.ref_root_pos[frame, 2] + self.offset_table[sample, frame, 2]
                min_height = torch.minimum(min_height, ref_z - tc.base_height_margin)
            by_height = root_pos[:, 2] < min_height
        terminated = terminated | by_tilt | by_height
        truncated = (phase >= 1.0 - _EPS) & ~terminated
        sparse = sparse + w.termination * terminated.to(torch.float32)
        return {
            "dense": dense, "sparse": sparse, "terms": terms,
            "terminated": terminated, "truncated": truncated,
            "by_keyframe": by_keyframe, "by_tilt": by_tilt, "by_height": by_height,
            "crossed": crossed, "crossed_kf": torch.where(crossed, k, -1), "next_kf": torch.where(crossed, k + 1, self.next_kf),
            "error_w": error_w, "keyframe_error_w": keyframe_error_w, "keyframe_miss_w": keyframe_miss_w,
            "local_error": local_err2.sqrt(), "joint_acc": joint_acc, "gravity": gravity, "tilt_error_xy": tilt_error_xy,
            # copies: the backend refreshes its state views in place at the next step
            "joint_pos": joint_pos.clone(), "joint_vel": joint_vel.clone(),
        }

    # ------------------------------------------------------------------------------------ resume
    # Per-world buffers that, with the physics state and the per-world model, decide every future step.
    _STATE_BUFFERS = ("phase", "frame", "sample", "next_kf", "episode_step", "prev_action", "prev_action2",
                      "prev_joint_vel", "odometry", "odom_origin", "odom_origin_quat", "obs_history",
                      "privileged", "target_history", "delay_lag", "delay_substeps", "push_timer", "start_frame",
                      "keyframe_missed")

    def _model_fields(self) -> list[str]:
        """The MjModel fields this env writes per world: the randomiser's and the terrain's."""
        names = list(self.randomizer.base)
        if self._terrain_fields is not None:
            names.append("geom_pos")
            if self._terrain_fields[1] is not None:
                names.append("geom_size")
        return names

    def state_dict(self) -> dict:
        """Everything that determines future steps, on the CPU, for a bit-exact resume (the trainer
        saves it with its checkpoint). Randomness is drawn from torch's global RNG, which the caller
        owns and restores itself (the trainer does); the randomiser's numpy RNG is re-seeded from it
        at every reset but is saved anyway."""
        ids = np.arange(self.num_envs)
        qpos, qvel = self.backend.get_state()
        return {
            "num_envs": self.num_envs,
            "qpos": torch.from_numpy(np.array(qpos, dtype=np.float64)),
            "qvel": torch.from_numpy(np.array(qvel, dtype=np.float64)),
            "model_fields": {name: np.array(self.backend.get_model_field(name, ids)) for name in self._model_fields()},
            "buffers": {name: getattr(self, name).detach().cpu().clone() for name in self._STATE_BUFFERS},
            "target_ptr": int(self.target_ptr),
            "termination_threshold": float(self.termination_threshold),
            "penalty_scale": float(self.penalty_scale),
            "penalty_curriculum": [self.penalty_curriculum_started, int(self.episodes_finished),
                                   int(self.episodes_terminated)],
            "randomizer_rng": self.randomizer.rng.bit_generator.state,
            "sampler": self.sampler.state_dict(),
            "own_states": None if self.own_states is None else self.own_states.state_dict(),
            "start_sampler": self.start_sampler.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restores `state_dict()` of an env built with the same config, data and number of worlds."""
        if int(state.get("num_envs", -1)) != self.num_envs:
            raise PipelineInputError("env state", "num_envs",
                                     f"checkpoint has {state.get('num_envs')} worlds, this env {self.num_envs}")
        ids = np.arange(self.num_envs)
        # model first: set_state's forward pass then sees each world's own masses and terrain
        for name, values in state["model_fields"].items():
            self.backend.set_model_field(name, ids, np.asarray(values))
        buffers = dict(state["buffers"])
        if "start_frame" not in buffers:  # states saved before it existed; exact at stage 1's fixed phase rate
            buffers["start_frame"] = (buffers["frame"] - buffers["episode_step"]).clamp(min=0)
        if "keyframe_missed" not in buffers:  # states saved before it existed: only the ψ sampler reads it
            buffers["keyframe_missed"] = torch.zeros_like(self.keyframe_missed)
        for name in self._STATE_BUFFERS:
            saved = buffers[name]
            current = getattr(self, name)
            if saved.shape != current.shape or saved.dtype != current.dtype:
                raise PipelineInputError("env state", name,
                                         f"expected {tuple(current.shape)} {current.dtype}, got {tuple(saved.shape)} {saved.dtype}")
            setattr(self, name, saved.to(self.device).clone())
        self.target_ptr = int(state["target_ptr"])
        self.termination_threshold = float(state["termination_threshold"])
        self.penalty_scale = float(state["penalty_scale"])
        started, finished, terminated = state["penalty_curriculum"]
        self.penalty_curriculum_started = bool(started)
        self._clear_episode_counts()
        self.episodes_finished += int(finished)
        self.episodes_terminated += int(terminated)
        self.randomizer.rng.bit_generator.state = state["randomizer_rng"]
        if "sampler" in state:  # absent in states saved before ψ sampling had a state
            self.sampler.load_state_dict(state["sampler"])
        if self.own_states is not None and state.get("own_states") is not None:
            self.own_states.load_state_dict(state["own_states"])
        if "start_sampler" in state:  # absent in states saved before adaptive start frames existed
            self.start_sampler.load_state_dict(state["start_sampler"])
        self.backend.set_state(ids, state["qpos"].numpy(), state["qvel"].numpy())

    # ------------------------------------------------------------------------------------ internals
    def _global_terms(self, err2, quat, target_quat):
        s2 = self.cfg.rewards.sigma2
        pos = torch.exp(-(err2 * self.inv_sigma2_pos).mean(-1))
        rot = R.rotation_kernel(quat, target_quat, s2.body_rot)
        feet = torch.exp(-err2[:, self.feet_idx].mean(-1) / s2.feet_pos)
        return pos, rot, feet

    def _delayed_control(self, target: torch.Tensor) -> torch.Tensor:
        if not self.randomizer.delay_enabled:
            return target
        self.target_ptr = (self.target_ptr + 1) % self.target_slots
        self.target_history[self.target_ptr] = target
        slots = (self.target_ptr - self.delay_lag) % self.target_slots  # (N, decimation)
        return self.target_history[slots, self.arange[:, None]]  # (N, decimation, J)

    def _apply_pushes(self) -> None:
        push = self.cfg.randomization.push
        if not (self.cfg.randomization.enabled and push.enabled):
            return
        self.push_timer -= self.control_dt
        due = self.push_timer <= 0
        if not bool(due.any()):
            return
        ids = due.nonzero().squeeze(-1)
        qvel = self.backend.qvel[ids].clone()
        kick = torch.rand(ids.numel(), 3, device=self.device) * 2 - 1
        qvel[:, 0:2] += push.max_vel_xy * kick[:, :2]
        qvel[:, 5] += push.max_vel_yaw * kick[:, 2]
        self.backend.set_state(ids, self.backend.qpos[ids].clone(), qvel, forward=False)  # the step's views: after it
        self.push_timer[ids] = self._push_interval(ids.numel())

    def _push_interval(self, n: int) -> torch.Tensor:
        lo, hi = self.cfg.randomization.push.interval_s
        return lo + (hi - lo) * torch.rand(n, device=self.device)

    def _frame_features(self, ids, gravity=None, noise=None):
        """The 92-d actor observation of one step, the critic's privileged tail and the odometry, for
        worlds `ids` (None: all). Odometry noise is drawn here unless given."""
        b = self.backend
        sel = (lambda x: x) if ids is None else (lambda x: x[ids])
        qpos, qvel = sel(b.qpos), sel(b.qvel)
        if gravity is None:
            gravity = projected_gravity(qpos[:, 3:7])
        step = sel(self.episode_step)
        fresh = quat_rotate_inverse(sel(self.odom_origin_quat), qpos[:, 0:3] - sel(self.odom_origin))
        if noise is None:
            noise = self._odometry_noise(fresh.shape[0])
        if noise is not None:
            fresh = fresh + noise
        odom = torch.where((step % self.odom_every == 0)[:, None], fresh, sel(self.odometry))
        phase, sample = sel(self.phase).to(torch.float32), sel(self.sample)
        frame_obs = torch.cat([
            qvel[:, 3:6], gravity, qpos[:, 7:] - self.default_joint_pos, qvel[:, 6:], sel(self.prev_action),
            phase[:, None], self.psi[sample][:, None], odom,
        ], dim=-1)
        lin_vel_b = quat_rotate_inverse(qpos[:, 3:7], qvel[:, 0:3])
        to_next = (self.kf_phase_padded[sel(self.next_kf)] - sel(self.phase)).clamp(max=1.0).to(torch.float32)
        privileged = torch.cat([lin_vel_b, self.ref_joint_pos[sel(self.frame)], qpos[:, 2:3], to_next[:, None]], dim=-1)
        return frame_obs, privileged, odom

    def _odometry_noise(self, n: int) -> torch.Tensor | None:
        """(n, 3) odometry noise, or None when it is off (then nothing is drawn from the RNG)."""
        std = self.cfg.observations.odometry_noise_std
        return std * torch.randn(n, 3, device=self.device) if std > 0 else None

    def _observe(self, gravity, noise):
        """Every world's next (obs_history, privileged, odometry), pure like `_score`."""
        frame_obs, privileged, odom = self._frame_features(None, gravity, noise)
        return torch.cat([self.obs_history[:, 1:], frame_obs[:, None]], dim=1), privileged, odom

    def _obs_dict(self) -> dict[str, torch.Tensor]:
        actor = self.obs_history.reshape(self.num_envs, -1)
        return {"actor": actor, "critic": torch.cat([actor, self.privileged], dim=-1)}

    def _perturb_start_pose(self, ids, qpos, qvel, frame, sample) -> torch.Tensor:
        """The pose of reference-state starts (frame > 0) turned and bent by `env.rsi_root_rot_noise` /
        `rsi_joint_pos_noise`, then lifted or lowered so that its lowest tracked foot is as high as the
        reference's: a turned base or bent knee otherwise starts with a foot in the floor or in the air."""
        late = (frame > 0).nonzero().squeeze(-1)
        if late.numel() == 0:
            return qpos
        n, dev = late.numel(), self.device
        pose = qpos[late].clone()
        if self.rsi_rot_noise is not None:
            turn = self.rsi_rot_noise * (2.0 * torch.rand(n, 3, device=dev) - 1.0)
            pose[:, 3:7] = quat_mul(pose[:, 3:7], quat_from_rotvec(turn))  # about the base's own axes
        if self.rsi_joint_noise > 0:
            bend = self.rsi_joint_noise * (2.0 * torch.rand(n, self.num_joints, device=dev) - 1.0)
            pose[:, 7:] = torch.clamp(pose[:, 7:] + bend, self.joint_pos_low, self.joint_pos_high)
        self.backend.set_state(ids[late], pose, qvel[late], forward=True)  # where the perturbed feet are
        feet_z = self.backend.site_pos[ids[late]][:, self.feet_idx, 2].amin(-1)
        ref_feet_z = self.ref_body_pos[frame[late]][:, self.feet_idx, 2].amin(-1) + self.offset_table[sample[late], frame[late], 2]
        pose[:, 2] += ref_feet_z - feet_z
        qpos = qpos.clone()
        qpos[late] = pose
        return qpos

    def _reset_worlds(self, ids: torch.Tensor) -> None:
        n, dev = ids.numel(), self.device
        sample = self.sampler.draw(ids)
        frame = torch.zeros(n, dtype=torch.long, device=dev)
        if self.cfg.rsi_prob > 0 and self.rsi_frame_table.numel() > 0:
            rsi = torch.rand(n, device=dev) < self.cfg.rsi_prob
            pick = self.start_sampler.draw(n)
            frame = torch.where(rsi, pick, frame)
        qpos = torch.cat([self.ref_root_pos[frame] + self.offset_table[sample, frame], self.ref_root_quat[frame],
                          self.ref_joint_pos[frame]], dim=-1)
        qvel = self.ref_qvel[frame].clone()
        qvel[:, 0:3] += self.offset_vel_table[sample, frame]
        if self.rsi_vel_noise is not None:  # None when off: no draw, the same random stream as without it
            started_late = (frame > 0)[:, None].to(qvel.dtype)
            qvel[:, 0:6] += started_late * self.rsi_vel_noise * (2.0 * torch.rand(n, 6, device=dev) - 1.0)
        if self.rsi_pose_noise:  # off: no draw, as above
            qpos = self._perturb_start_pose(ids, qpos, qvel, frame, sample)
        own, restart = None, None
        if self.own_states is not None and len(self.own_states) > 0:  # empty: no draw, as with the option off
            own = (torch.rand(n, device=dev) < self.cfg.own_state_starts.prob).nonzero().squeeze(-1)
            restart = self.own_states.draw(own.numel())
            sample[own], frame[own] = restart["sample"], restart["frame"]
            qpos[own], qvel[own] = restart["qpos"].to(qpos.dtype), restart["qvel"].to(qvel.dtype)
        self.backend.set_state(ids, qpos, qvel, forward=False)  # observations read qpos/qvel only

        ids_np = ids.cpu().numpy()
        sample_np = sample.cpu().numpy()
        if self._terrain_fields is not None:
            self.backend.set_model_field("geom_pos", ids_np, self._terrain_fields[0][sample_np])
            if self._terrain_fields[1] is not None:
                self.backend.set_model_field("geom_size", ids_np, self._terrain_fields[1][sample_np])
        delay = self.randomizer.apply(ids_np)  # (n,) seconds of control delay
        d = torch.as_tensor(np.round(delay / self.sim_dt), dtype=torch.long, device=dev)
        self.delay_substeps[ids] = d
        sub = torch.arange(self.decimation, device=dev)
        self.delay_lag[ids] = torch.clamp(torch.div(d[:, None] - sub + self.decimation - 1, self.decimation,
                                                    rounding_mode="floor"), min=0)
        self.target_history[:, ids] = self.ref_joint_pos[frame]

        self.sample[ids] = sample
        self.frame[ids] = frame
        self.start_frame[ids] = frame
        self.keyframe_missed[ids] = False
        self.phase[ids] = frame.to(torch.float64) / (self.num_frames - 1)
        self.next_kf[ids] = torch.searchsorted(self.kf_frames, frame, right=True)
        self.episode_step[ids] = 0
        self.prev_action[ids] = 0.0
        self.prev_action2[ids] = 0.0
        self.prev_joint_vel[ids] = qvel[:, 6:]
        self.odom_origin[ids] = self.ref_root_pos[0] + self.offset_table[sample, 0]
        self.odom_origin_quat[ids] = yaw_quat(self.ref_root_quat[0])
        self.push_timer[ids] = self._push_interval(n)
        frame_obs, privileged, odom = self._frame_features(ids)
        self.odometry[ids] = odom
        hist = self.obs_history.clone()
        hist[ids] = frame_obs[:, None].expand(-1, self.cfg.observations.history, -1)
        self.obs_history = hist
        priv = self.privileged.clone()
        priv[ids] = privileged
        self.privileged = priv
        if own is not None and own.numel():
            # the recorded world's phase, history and odometry, so the policy sees what it saw there
            # (episode_step restarts at 0: only the odometry's update cadence reads it)
            worlds = ids[own]
            for name in OWN_STATE_FIELDS:
                if name not in ("qpos", "qvel", "sample", "frame"):
                    getattr(self, name)[worlds] = restart[name]


__all__ = ["TrackingEnv", "FRAME_OBS_DIM"]
