"""How the tracking env starts episodes: ψ sample and start frame, the reference state (plus noise) or
one of the policy's own recorded states, the terrain of the sample, the randomisation; and what the
samplers learn from the episodes that end."""

from __future__ import annotations

import torch

from pipeline.envs.own_states import FIELDS as OWN_STATE_FIELDS
from pipeline.envs.torch_math import quat_from_rotvec, quat_mul, yaw_quat


class TrackingResets:
    """Mixin of `TrackingEnv`: its resets and the samplers' feedback."""

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
        at_go = None
        if self.go_states is not None:  # off: no draw, as above
            at_go = ((frame == 0) & (torch.rand(n, device=dev) < self.cfg.go_starts.prob)).nonzero().squeeze(-1)
            stance = self.ref_root_pos[0] + self.offset_table[sample[at_go], 0]
            go_qpos, go_qvel = self.go_states.place(at_go.numel(), stance, self.start_heading_quat)
            qpos, qvel = qpos.clone(), qvel.clone()
            qpos[at_go], qvel[at_go] = go_qpos.to(qpos.dtype), go_qvel.to(qvel.dtype)
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
        held = self.ref_joint_pos[frame]
        if at_go is not None and at_go.numel():  # the motors hold about where the balance policy left them
            held = held.clone()
            held[at_go] = qpos[at_go, 7:].to(held.dtype)
        self._randomize_worlds(ids, held)

        self.sample[ids] = sample
        self.frame[ids] = frame
        self.start_frame[ids] = frame
        self.keyframe_missed[ids] = False
        self.phase[ids] = frame.to(torch.float64) / (self.num_frames - 1)
        self.next_kf[ids] = torch.searchsorted(self.kf_frames, frame, right=True)
        self._restart_episodes(ids, qvel[:, 6:])
        self.odom_origin[ids] = self.ref_root_pos[0] + self.offset_table[sample, 0]
        self.odom_origin_quat[ids] = self.start_heading_quat
        if at_go is not None and at_go.numel():  # a chain's odometry counts from the pose at the go
            self.odom_origin[ids[at_go]] = qpos[at_go, 0:3].to(self.odom_origin.dtype)
            self.odom_origin_quat[ids[at_go]] = yaw_quat(qpos[at_go, 3:7]).to(self.odom_origin_quat.dtype)
        frame_obs, privileged, odom = self._frame_features(ids)
        self.odometry[ids] = odom
        self._restart_observations(ids, frame_obs, privileged)
        if own is not None and own.numel():
            # the recorded world's phase, history and odometry, so the policy sees what it saw there
            # (episode_step restarts at 0: only the odometry's update cadence reads it)
            worlds = ids[own]
            for name in OWN_STATE_FIELDS:
                if name not in ("qpos", "qvel", "sample", "frame"):
                    getattr(self, name)[worlds] = restart[name]
