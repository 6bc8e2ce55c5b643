"""What the tracking policy and its critics observe: one history step of proprioception, phase, ψ and
odometry (the odometry held between its updates, noisy when asked), the critics' privileged tail, and
where each quantity sits (the layout the export and the trainer read)."""

from __future__ import annotations

import torch

from pipeline.envs.robot_env import proprio_dim
from pipeline.envs.torch_math import projected_gravity, quat_rotate_inverse

FRAME_OBS_DIM = proprio_dim(27) + 1 + 1 + 3  # per history step (for the 27-joint G1): proprioception, phase, ψ, odometry


class TrackingObservations:
    """Mixin of `TrackingEnv`: its observations."""

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
        frame_obs = torch.cat([self._proprio(qpos, qvel, gravity, sel(self.prev_action)),
                               phase[:, None], self.psi[sample][:, None], odom], dim=-1)
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

