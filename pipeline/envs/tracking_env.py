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

import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs import rewards as R
from pipeline.envs.config import EnvConfig
from pipeline.envs.go_starts import GoStates
from pipeline.envs.handoff_catch import Handoff, HandoffCatch
from pipeline.envs.robot_env import PENALTY_TERMS, RobotEnv
from pipeline.envs.sampling import SampleSampler
from pipeline.envs.scene import build_scene, terrain_fields_per_sample
from pipeline.envs.torch_math import projected_gravity, quat_conjugate, quat_mul, quat_rotate_inverse
from pipeline.envs.tracking_observations import FRAME_OBS_DIM, TrackingObservations
from pipeline.envs.tracking_reference import TrackingReference
from pipeline.envs.tracking_resets import TrackingResets
from pipeline.keyframes.tracking_data import TrackingData
from pipeline.robot.g1 import load_robot_config

# The dense group's terms in the order `_score` stacks them (the global ones only in dense tracking).
_DENSE_TERMS = ("local_body_pos", "local_body_rot", "local_joint_pos", "root_tilt", "root_ang_vel") + PENALTY_TERMS
_GLOBAL_TERMS = ("global_body_pos", "global_body_rot", "global_feet_pos")
_EPS = 1e-6


class TrackingEnv(TrackingObservations, TrackingReference, TrackingResets, RobotEnv):
    _STATE_BUFFERS = RobotEnv.SHARED_BUFFERS + ("phase", "frame", "sample", "next_kf", "odometry", "odom_origin",
                                                "odom_origin_quat", "start_frame", "keyframe_missed")

    def __init__(self, cfg: EnvConfig, data: TrackingData, *, num_envs: int, backend="cpu", device="cpu",
                 seed: int = 0, task=None, go_states: dict | None = None, handoff: Handoff | None = None):
        self.data = data
        self.robot = load_robot_config()
        source = f"task {data.task}"
        self._check_data(data, source)
        model, terrain_layout = build_scene(data, task, source, cfg.physics)
        super().__init__(cfg, model, num_envs=num_envs, backend=backend, device=device, source=source)
        n = self.num_envs
        # All randomness comes from torch's global RNG (seeded by the caller): a trainer that saves
        # and restores it replays the same episodes after a resume. `seed` stays for the contract.
        self.seed = seed
        # episodes end at the chain's handoff when the task is paid for what the balance policy makes of it there
        catch_weight = cfg.rewards.weights.handoff_catch
        if catch_weight and handoff is None:
            raise PipelineInputError("env", "rewards.weights.handoff_catch", "needs the chain's handoff: the task's "
                                     "clip.handoff_after_landing_s and the balance policy of params.yaml balance.out")
        self.end_phase = float(handoff.phase) if catch_weight else 1.0
        self._precompute_reference()
        self._precompute_robot()
        self.handoff_catch = None
        if catch_weight:
            self.handoff_catch = HandoffCatch(handoff.balance_checkpoint, self.default_joint_pos, self.device)
            self.handoff_ground = self._handoff_ground()
        self.go_states = None  # starts at t = 0 where the balance policy hands over (envs/go_starts.py)
        if cfg.go_starts.prob > 0:
            if go_states is None:
                raise PipelineInputError("env", "go_starts.prob", "needs the balance policy's go states (the training "
                                         "stages record them from params.yaml balance.out)")
            self.go_states = GoStates(go_states, self.model.nq, self.model.nv, self.device)
        self._start_randomizer()
        self.sampler = SampleSampler(cfg.sampling, data.psi, data.psi_raw, n, self.device)
        self._terrain_fields = terrain_fields_per_sample(self.model, terrain_layout, data.psi, source)

        self.actor_obs_dim = FRAME_OBS_DIM * cfg.observations.history
        self.critic_obs_dim = self.actor_obs_dim + 3 + self.num_joints + 1 + 1

        self.termination_threshold = float(cfg.terminations.keyframe_error.start)
        self.penalty_scale = 1.0  # the paper's weights until a trainer's curriculum says otherwise
        # The per-step tensor work, compiled into a few fused kernels when asked (`env.compile`): on a
        # GPU the eager step is ~450 small launches whose host time, not the worlds, sets its speed.
        self._score_fn, self._observe_fn = self._score, self._observe
        if cfg.compile:
            self._score_fn = torch.compile(self._score, fullgraph=True, dynamic=False)
            self._observe_fn = torch.compile(self._observe, fullgraph=True, dynamic=False)
        self.penalty_curriculum_started = False
        # episodes finished / terminated since the last curriculum update (the penalty curriculum's input)
        self._clear_episode_counts()
        self._alloc_state()

    # ------------------------------------------------------------------------------------ set-up
    def _handoff_ground(self) -> torch.Tensor:
        """(S,) per ψ sample, the height of the ground the robot is handed over on: how far the feet of the
        last keyframe at or before the handoff sit above the feet of the reference's first frame."""
        k = int(torch.searchsorted(self.kf_phase, torch.tensor(self.end_phase + _EPS, dtype=torch.float64,
                                                              device=self.device), right=True)) - 1
        if k < 0:
            raise PipelineInputError(f"task {self.data.task}", "clip.handoff_after_landing_s",
                                     "the handoff comes before the task's first keyframe")
        first = self.ref_body_pos[0, self.feet_idx, 2].mean()
        return self.kf_target_pos[:, k][:, self.feet_idx, 2].mean(-1) - first

    def _precompute_robot(self) -> None:
        super()._precompute_robot()
        cfg = self.cfg.rewards
        names = self.robot.tracked_body_names
        unknown = [b for b in cfg.lower_body if b not in names]
        if unknown:
            raise PipelineInputError("env", "rewards.lower_body", f"unknown tracked bodies {unknown}")
        s = cfg.sigma2
        inv = [1.0 / (s.lower_body_pos if b in cfg.lower_body else s.upper_body_pos) for b in names]
        self.inv_sigma2_pos = self._tensor(inv)
        term = self.cfg.terminations
        self.height_termination = term.base_height_enabled and self.data.task not in term.base_height_exempt_tasks
        self.odom_every = max(1, int(round(1.0 / (self.cfg.observations.odometry_rate_hz * self.control_dt))))

    def _alloc_state(self) -> None:
        n, dev = self.num_envs, self.device
        self._alloc_shared_state(FRAME_OBS_DIM, self.critic_obs_dim - self.actor_obs_dim)
        self.phase = torch.zeros(n, dtype=torch.float64, device=dev)
        self.frame = torch.zeros(n, dtype=torch.long, device=dev)
        self.sample = torch.zeros(n, dtype=torch.long, device=dev)
        self.next_kf = torch.zeros(n, dtype=torch.long, device=dev)
        self.start_frame = torch.zeros(n, dtype=torch.long, device=dev)
        # the episode crossed a keyframe with a body-mean error over the success test's threshold
        self.keyframe_missed = torch.zeros(n, dtype=torch.bool, device=dev)
        self.odometry, self.odom_origin = torch.zeros(n, 3, device=dev), torch.zeros(n, 3, device=dev)
        self.odom_origin_quat = torch.zeros(n, 4, device=dev)
        self.odom_origin_quat[:, 0] = 1.0

    # ------------------------------------------------------------------------------------ API
    def _phase_rate(self) -> float:
        return float(self.dphi)

    def _action_offset_kind(self) -> str:
        return self.cfg.action_offset

    def _push_prior(self) -> bool:
        return self.push_table is not None

    def curriculum_stats(self) -> dict:
        stats = {"termination_threshold": float(self.termination_threshold), **super().curriculum_stats()}
        if self.sampler.cfg.mode == "curriculum":
            stats["psi_level"] = self.sampler.mean_level()
            stats["psi_level_success"] = [round(v, 4) for v in self.sampler.level_success.tolist()]  # history only
            if self.sampler.cfg.split_sides:
                stats["psi_level_side"] = list(self.sampler.level_side)  # 0: short of the clip's ψ, 1: beyond
        return stats

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

    def _dense_term_names(self) -> tuple[str, ...]:
        return _DENSE_TERMS + (_GLOBAL_TERMS if self.cfg.variant.tracking == "dense" else ())

    def _keyframe_error_exceeded(self, err2: torch.Tensor) -> torch.Tensor:
        """(N, bodies) squared position errors -> (N,) past the keyframe-error termination threshold."""
        if self.cfg.terminations.keyframe_error.measure == "mean":
            return err2.sqrt().mean(-1) > self._threshold_tensor
        return err2.max(-1).values > self._threshold_tensor

    def update_curriculum(self, progress: float) -> float:
        """Called once per training iteration. Sets the keyframe-error termination threshold
        (returned) from training progress p ∈ [0, 1], and the dense penalty scale (`penalty_scale`)
        from the share of episodes that fell since the last call (see `PenaltyCurriculum`)."""
        self._update_penalty_curriculum()
        return self.set_termination_threshold(self.cfg.terminations.keyframe_error.threshold_at(progress))

    def _action_offset(self, frame: torch.Tensor) -> torch.Tensor:
        """Joint targets at a zero action: the default pose, or the reference's joints at `frame`
        (with the feedforward of envs/feedforward.py for "feedforward", and the push prior's w(ψ) · push
        of the sample each world tracks when the data has one)."""
        if self.cfg.action_offset == "default":
            return self.default_joint_pos
        if self.push_table is None:
            return self.joint_target_table[frame]
        return self.joint_target_table[frame] + self.push_weight[self.sample][:, None] * self.push_table[frame]

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
        sparse, dense = s["sparse"], s["dense"]
        catch = None
        if self.handoff_catch is not None:
            catch = torch.full_like(sparse, float("nan"))  # NaN: not handed over this step
            handed = truncated.nonzero().squeeze(-1)
            if handed.numel():
                catch[handed] = self.handoff_catch(b.qpos[handed], b.qvel[handed], self.handoff_ground[self.sample[handed]])
                sparse = sparse.index_add(0, handed, self.cfg.rewards.weights.handoff_catch * catch[handed])
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
        if catch is not None:
            info["handoff_catch"] = catch  # the training log's mean catch at the handoff
        self._count_episodes(done, terminated)
        if bool(done.any()):
            ended = done.nonzero().squeeze(-1)
            self._record_psi_outcomes(ended, s)
            self.start_sampler.record(self.start_frame[ended], terminated[ended])
            self._reset_worlds(ended)
        return self._obs_dict(), {"sparse": sparse, "dense": dense}, terminated, truncated, info

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
            **self._penalty_terms(joint_pos, joint_vel, joint_acc, torque, site_quat[:, self.feet_idx], foot_contact, action),
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
        min_height = None
        if self.height_termination:
            min_height = torch.full_like(root_pos[:, 2], tc.min_base_height)
            if tc.relative_to_reference:
                ref_z = self.ref_root_pos[frame, 2] + self.offset_table[sample, frame, 2]
                min_height = torch.minimum(min_height, ref_z - tc.base_height_margin)
        by_tilt, by_height = self._falls(tilt_xy, root_pos[:, 2], tc.max_tilt, min_height)
        terminated = terminated | by_tilt | by_height
        truncated = (phase >= self.end_phase - _EPS) & ~terminated
        sparse = sparse + w.termination * terminated.to(torch.float32)
        if w.handoff:  # arriving where the balance policy can take over: upright and slow when the phase ends
            still = torch.exp(-(gravity[:, :2] ** 2).sum(-1) / s2.handoff_tilt - (qvel[:, 0:2] ** 2).sum(-1) / s2.handoff_speed)
            sparse = sparse + torch.where(truncated, w.handoff * still, 0.0)
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
    def _model_fields(self) -> list[str]:
        """The MjModel fields this env writes per world: the randomiser's and the terrain's."""
        names = super()._model_fields()
        if self._terrain_fields is not None:
            names.append("geom_pos")
            if self._terrain_fields[1] is not None:
                names.append("geom_size")
        return names

    def _task_state(self) -> dict:
        return {"termination_threshold": float(self.termination_threshold), "sampler": self.sampler.state_dict(),
                "own_states": None if self.own_states is None else self.own_states.state_dict(),
                "start_sampler": self.start_sampler.state_dict()}

    def _upgrade_buffers(self, buffers: dict) -> dict:
        if "start_frame" not in buffers:  # states saved before it existed; exact at stage 1's fixed phase rate
            buffers["start_frame"] = (buffers["frame"] - buffers["episode_step"]).clamp(min=0)
        if "keyframe_missed" not in buffers:  # states saved before it existed: only the ψ sampler reads it
            buffers["keyframe_missed"] = torch.zeros_like(self.keyframe_missed)
        return buffers

    def _load_task_state(self, state: dict) -> None:
        self.termination_threshold = float(state["termination_threshold"])
        if "sampler" in state:  # absent in states saved before ψ sampling had a state
            self.sampler.load_state_dict(state["sampler"])
        if self.own_states is not None and state.get("own_states") is not None:
            self.own_states.load_state_dict(state["own_states"])
        if "start_sampler" in state:  # absent in states saved before adaptive start frames existed
            self.start_sampler.load_state_dict(state["start_sampler"])

    # ------------------------------------------------------------------------------------ internals
    def _global_terms(self, err2, quat, target_quat):
        s2 = self.cfg.rewards.sigma2
        pos = torch.exp(-(err2 * self.inv_sigma2_pos).mean(-1))
        rot = R.rotation_kernel(quat, target_quat, s2.body_rot)
        feet = torch.exp(-err2[:, self.feet_idx].mean(-1) / s2.feet_pos)
        return pos, rot, feet



__all__ = ["TrackingEnv", "FRAME_OBS_DIM"]
