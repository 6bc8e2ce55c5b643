"""The balance env: the G1 holds its stance on flat ground and comes back to it after pushes and landings.

The policy sees proprioception only (what `adamimic deploy` measures: no odometry, no phase) and
aims the joints at the default pose plus `action_scale · action`. Episodes start at the stance at
rest with noise, lowered from a little above it, or in a recorded state (the task policies' own
ends: `pipeline/balance/starts.py`), under the paper's domain randomisation and pushes every 1–3 s.
The dense group pays upright, stance height, stillness, the default pose, each foot back under
the pelvis where the stance puts it and (where weighted) the heading the episode started with, less the
shared penalties; the sparse group is the fall alone.
An episode ends in a fall (`falls.fall_flags`) or, truncated, after `episode_s`.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from pipeline.common.errors import PipelineInputError
from pipeline.envs import rewards as R
from pipeline.envs.balance_config import BalanceEnvConfig
from pipeline.envs.robot_env import PENALTY_TERMS, RobotEnv, proprio_dim, proprio_frame
from pipeline.envs.torch_math import projected_gravity, quat_rotate_inverse, wrap_angle, yaw_angle, yaw_quat
from pipeline.robot.g1 import default_qpos, load_robot_config

_DENSE_TERMS = ("upright", "base_height", "lin_vel", "ang_vel", "default_pose", "stance", "heading") + PENALTY_TERMS
PRIVILEGED_DIM = 3 + 1 + 2  # base linear velocity (base frame), pelvis height, feet in contact


def balance_actuation(cfg: BalanceEnvConfig, robot=None) -> tuple[np.ndarray, np.ndarray]:
    """(J,) joint targets of a zero action and (J,) action scale: the env's and the exported graph's."""
    from pipeline.robot.dynamics import stance_torques

    robot = robot or load_robot_config()
    target = np.array(robot.default_joint_pos, dtype=np.float64)
    if cfg.stance_feedforward:
        target = target + stance_torques(robot) / robot.kp
    scale = np.array(robot.action_scale, dtype=np.float64)
    scale[[robot.joint_names.index(name) for name in cfg.frozen_joints]] = 0.0
    return target, scale


def balance_features(qpos, qvel, gravity, foot_contact, prev_action, default_joint_pos):
    """(frame, privileged) of the balance env's observations: one step of proprioception, and the critic's
    base velocity (base frame), pelvis height (`qpos` z: the ground is at 0) and feet in contact."""
    frame = proprio_frame(qpos, qvel, gravity, prev_action, default_joint_pos)
    lin_vel_b = quat_rotate_inverse(qpos[:, 3:7], qvel[:, 0:3])
    return frame, torch.cat([lin_vel_b, qpos[:, 2:3], foot_contact.to(torch.float32)], dim=-1)


def flat_scene(physics: str, source: str) -> mujoco.MjModel:
    from pipeline.sim.model import build_sim_model

    return build_sim_model(physics=load_robot_config().physics(physics, source, "physics"))


class BalanceEnv(RobotEnv):
    _STATE_BUFFERS = RobotEnv.SHARED_BUFFERS + ("start_yaw",)

    def __init__(self, cfg: BalanceEnvConfig, *, num_envs: int, start_states: dict | None = None, backend="cpu",
                 device="cpu"):
        source = "balance.env"
        super().__init__(cfg, flat_scene(cfg.physics, source), num_envs=num_envs, backend=backend, device=device,
                         source=source)
        self._precompute_robot()
        stance_target, action_scale = balance_actuation(cfg, self.robot)
        self.stance_target, self.action_scale = self._tensor(stance_target), self._tensor(action_scale)
        self._start_randomizer()
        self.actor_obs_dim = proprio_dim(self.num_joints) * cfg.observations.history
        self.critic_obs_dim = self.actor_obs_dim + PRIVILEGED_DIM
        self.max_steps = int(round(cfg.episode_s / self.control_dt))
        self._stance()
        self.start_states = self._check_start_states(start_states)
        self.penalty_scale = 1.0
        self.penalty_curriculum_started = False
        self._clear_episode_counts()
        self._alloc_shared_state(proprio_dim(self.num_joints), PRIVILEGED_DIM)
        self.start_yaw = torch.zeros(self.num_envs, device=self.device)  # each episode's first heading
        self.difficulty = 1.0  # full pushes, delays and recorded starts until a trainer's curriculum says otherwise

    # ------------------------------------------------------------------------------------ set-up
    def _stance(self) -> None:
        """The default pose standing on the floor, and where it puts each foot under the pelvis."""
        model = self.model
        data = mujoco.MjData(model)
        data.qpos[:] = default_qpos(self.robot)
        mujoco.mj_kinematics(model, data)
        sites = [model.site(n).id for n in self.robot.tracked_site_names]
        feet = data.site_xpos[sites][self.feet_idx.cpu().numpy()] - data.qpos[:3]
        self.stance_qpos = self._tensor(data.qpos)
        self.stance_height = float(self.robot.default_root_height)
        self.stance_feet_xy = self._tensor(feet[:, :2])  # (2, 2): the default pose's base is not turned

    def _check_start_states(self, states: dict | None) -> dict | None:
        if states is None or len(states["qpos"]) == 0:
            return None
        qpos, qvel = np.asarray(states["qpos"]), np.asarray(states["qvel"])
        if qpos.ndim != 2 or qpos.shape[1] != self.model.nq or qvel.shape != (len(qpos), self.model.nv):
            raise PipelineInputError(states.get("source", "start states"), "qpos",
                                     f"expected (M, {self.model.nq}) and (M, {self.model.nv}), got {qpos.shape}, {qvel.shape}")
        return {"qpos": self._tensor(qpos), "qvel": self._tensor(qvel)}

    # ------------------------------------------------------------------------------------ API
    def obs_layout(self) -> dict:
        j = self.num_joints
        names = [("base_ang_vel", 3), ("projected_gravity", 3), ("joint_pos_rel", j), ("joint_vel", j), ("prev_action", j)]
        out, start = {}, 0
        for name, size in names:
            out[name] = [start, start + size]
            start += size
        return {"history": self.cfg.observations.history, "frame_dim": start, "actor_frame": out,
                "critic_privileged": {"base_lin_vel": [self.actor_obs_dim, self.actor_obs_dim + 3],
                                      "base_height": [self.actor_obs_dim + 3, self.actor_obs_dim + 4],
                                      "feet_contact": [self.actor_obs_dim + 4, self.actor_obs_dim + 6]}}

    def update_curriculum(self, progress: float) -> float:
        """Once per training iteration: the penalty curriculum, and the pushes, delays and recorded starts at
        `BalanceCurriculum.level(progress)` of their configured values (returned)."""
        self._update_penalty_curriculum()
        self.difficulty = self.delay_scale = self.push_scale = self.cfg.curriculum.level(progress)
        return self.difficulty

    def _dense_term_names(self) -> tuple[str, ...]:
        # a heading weight of 0 leaves the term out of the sum: the policies trained before it sum the same
        return tuple(n for n in _DENSE_TERMS if n != "heading" or self.cfg.rewards.weights.heading != 0.0)

    def _upgrade_buffers(self, buffers: dict) -> dict:
        if "start_yaw" not in buffers:  # states saved before the heading reward: the stance's heading
            buffers["start_yaw"] = torch.zeros_like(self.start_yaw)
        return buffers

    def _step(self, action: torch.Tensor, phase_rate_offset=None):
        action = action.to(self.device, torch.float32).clamp(-self.cfg.action_clip, self.cfg.action_clip)
        self.episode_step += 1
        target = self.stance_target + self.action_scale * action
        self._apply_pushes()
        self.backend.step(self._delayed_control(target))
        b = self.backend
        s = self._score(b.qpos, b.qvel, b.site_pos, b.site_quat, b.actuator_force, b.foot_contact, action)
        terminated, truncated = s["terminated"], s["truncated"]
        self.prev_action2, self.prev_action = self.prev_action, action
        self.prev_joint_vel = s["joint_vel"]
        frame, self.privileged = self._features(b.qpos, b.qvel, s["gravity"], b.foot_contact, self.prev_action)
        self.obs_history = torch.cat([self.obs_history[:, 1:], frame[:, None]], dim=1)
        final_obs = self._obs_dict()
        done = terminated | truncated
        self._count_episodes(done, terminated)
        info = {"final_obs": final_obs, "terms": s["terms"], "joint_pos": s["joint_pos"],
                "terminated_by": {"tilt": s["by_tilt"], "base_height": s["by_height"]}}
        if bool(done.any()):
            self._reset_worlds(done.nonzero().squeeze(-1))
        return self._obs_dict(), {"sparse": s["sparse"], "dense": s["dense"]}, terminated, truncated, info

    def _features(self, qpos, qvel, gravity, foot_contact, prev_action):
        return balance_features(qpos, qvel, gravity, foot_contact, prev_action, self.default_joint_pos)

    def _score(self, qpos, qvel, site_pos, site_quat, torque, foot_contact, action) -> dict:
        cfg, s2 = self.cfg, self.cfg.rewards.sigma2
        root_pos, root_quat = qpos[:, 0:3], qpos[:, 3:7]
        gravity = projected_gravity(root_quat)
        joint_pos, joint_vel = qpos[:, 7:], qvel[:, 6:]
        joint_acc = (joint_vel - self.prev_joint_vel) / self.control_dt
        heading = yaw_quat(root_quat)[:, None].expand(-1, self.feet_idx.numel(), -1)
        feet = quat_rotate_inverse(heading, site_pos[:, self.feet_idx] - root_pos[:, None])[..., :2]
        terms = {
            "upright": torch.exp(-(gravity[:, :2] ** 2).sum(-1) / s2.upright),
            "base_height": torch.exp(-((root_pos[:, 2] - self.stance_height) ** 2) / s2.base_height),
            "lin_vel": torch.exp(-(qvel[:, 0:2] ** 2).sum(-1) / s2.lin_vel),
            "ang_vel": torch.exp(-(qvel[:, 3:6] ** 2).sum(-1) / s2.ang_vel),
            "default_pose": R.joint_kernel(joint_pos, self.default_joint_pos, s2.default_pose),
            "stance": torch.exp(-((feet - self.stance_feet_xy) ** 2).sum(-1).mean(-1) / s2.stance),
            "heading": torch.exp(-wrap_angle(yaw_angle(root_quat) - self.start_yaw) ** 2 / s2.heading),
            **self._penalty_terms(joint_pos, joint_vel, joint_acc, torque, site_quat[:, self.feet_idx], foot_contact, action),
        }
        dense = (torch.stack([terms[name] for name in self._dense_term_names()], -1) * self._dense_weights).sum(-1)
        fc = cfg.terminations
        by_tilt, by_height = self._falls(gravity[:, :2], root_pos[:, 2], fc.max_tilt, fc.min_base_height)
        terminated = by_tilt | by_height
        truncated = (self.episode_step >= self.max_steps) & ~terminated
        sparse = cfg.rewards.weights.termination * terminated.to(torch.float32)
        return {"dense": dense, "sparse": sparse, "terms": terms, "terminated": terminated, "truncated": truncated,
                "by_tilt": by_tilt, "by_height": by_height, "gravity": gravity, "joint_vel": joint_vel.clone(),
                "joint_pos": joint_pos.clone()}

    # ------------------------------------------------------------------------------------ resets
    def _reset_worlds(self, ids: torch.Tensor) -> None:
        n, dev, st = ids.numel(), self.device, self.cfg.starts
        u = lambda *shape: 2.0 * torch.rand(*shape, device=dev) - 1.0  # noqa: E731
        qpos = self.stance_qpos.expand(n, -1).clone()
        qvel = torch.zeros(n, self.model.nv, device=dev)
        qpos[:, 7:] = torch.clamp(qpos[:, 7:] + st.joint_pos_noise * u(n, self.num_joints),
                                  self.joint_pos_low, self.joint_pos_high)
        qvel[:, 0:2] = st.lin_vel_noise * u(n, 2)
        qvel[:, 3:6] = st.ang_vel_noise * u(n, 3)
        kind = torch.rand(n, device=dev)
        drop = (kind < st.drop_prob).nonzero().squeeze(-1)
        qpos[drop, 2] += st.drop_height * torch.rand(drop.numel(), device=dev)
        if self.start_states is not None:
            recorded = (kind >= 1.0 - st.states_prob * self.difficulty).nonzero().squeeze(-1)
            pick = torch.randint(0, self.start_states["qpos"].shape[0], (recorded.numel(),), device=dev)
            lo, hi = st.state_vel_scale
            scale = lo + (hi - lo) * torch.rand(recorded.numel(), 1, device=dev)
            qpos[recorded] = self.start_states["qpos"][pick]
            qvel[recorded] = self.start_states["qvel"][pick] * scale
        start_yaw = self.start_yaw.clone()  # a new tensor: callers hold the old
        start_yaw[ids] = yaw_angle(qpos[:, 3:7])
        self.start_yaw = start_yaw
        self.backend.set_state(ids, qpos, qvel, forward=False)  # observations read qpos/qvel only
        self._randomize_worlds(ids, self.stance_target)
        self._restart_episodes(ids, qvel[:, 6:])
        gravity = projected_gravity(qpos[:, 3:7])
        contact = torch.zeros(n, 2, dtype=torch.bool, device=dev)  # not yet known before the first step
        self._restart_observations(ids, *self._features(qpos, qvel, gravity, contact, self.prev_action[ids]))


__all__ = ["BalanceEnv", "PRIVILEGED_DIM"]
