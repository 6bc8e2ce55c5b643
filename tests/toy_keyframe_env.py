"""A small keyframe-reaching toy env for the RL tests, following the TrackingEnv contract: a 2-D point mass must be
near keyframe targets at two fixed steps (sparse group, like AdaMimic's keyframe rewards) while following a
reference path and not using large actions (dense group); leaving the arena terminates with a penalty; the episode
times out after `horizon` steps. It draws all randomness from torch's global RNG. Also: a small PPO config, a
stage-1 policy and critic for it, the policy metadata, and the deterministic policy's mean return."""

from __future__ import annotations

import torch

from pipeline.rl.config import TrainConfig
from pipeline.rl.networks import DoubleCritic, Stage1Policy


class ToyKeyframeEnv:
    horizon = 16
    keyframes = {7: torch.tensor([1.0, 0.0]), 15: torch.tensor([1.0, 1.0])}

    def __init__(self, num_envs: int = 64):
        self.num_envs, self.action_dim = num_envs, 2
        self.actor_obs_dim, self.critic_obs_dim = 3, 4
        self.dphi = 1.0 / self.horizon
        self.obs_layout = {"pos": 2, "phase": 1}
        self.joint_names = ["x", "y"]
        self.pos = torch.zeros(num_envs, 2)
        self.t = torch.zeros(num_envs, dtype=torch.long)
        self.curriculum_calls = []

    # the trainer's contract (pipeline/envs/spec.py); no state to save: restarted at checkpoint boundaries
    def spec(self):
        from pipeline.envs.spec import EnvSpec

        return EnvSpec(num_envs=self.num_envs, action_dim=self.action_dim, actor_obs_dim=self.actor_obs_dim,
                       critic_obs_dim=self.critic_obs_dim, joint_names=tuple(self.joint_names),
                       obs_layout=self.obs_layout, phase_rate=self.dphi, resumable=False)

    def update_curriculum(self, progress):
        self.curriculum_calls.append(progress)

    def curriculum_stats(self):
        return {}

    def pinned_observation_stats(self):
        return []

    def _reference(self, t):
        # straight line to the first keyframe, then up to the second
        s = (t.float() + 1) / 8.0
        first = torch.stack([s.clamp(max=1.0), torch.zeros_like(s)], -1)
        return first + torch.stack([torch.zeros_like(s), (s - 1.0).clamp(0.0, 1.0)], -1)

    def _obs(self):
        phase = (self.t.float() / self.horizon).unsqueeze(-1)
        actor = torch.cat([self.pos, phase], -1)
        return {"actor": actor, "critic": torch.cat([actor, phase**2], -1)}

    def _reset(self, ids):
        self.pos[ids] = 0.05 * torch.randn(len(ids), 2)
        self.t[ids] = 0

    def reset(self):
        self._reset(torch.arange(self.num_envs))
        return self._obs()

    def step(self, action, phase_rate_offset=None):
        action = action.clamp(-1.0, 1.0)
        self.pos = self.pos + 0.25 * action
        sparse = torch.zeros(self.num_envs)
        crossed = torch.zeros(self.num_envs, dtype=torch.bool)
        err = torch.zeros(self.num_envs, 1)
        for step, target in self.keyframes.items():
            hit = self.t == step
            dist = (self.pos - target).norm(dim=-1)
            sparse += hit * 10.0 * torch.exp(-(dist**2) / 0.1)
            crossed |= hit
            err[hit, 0] = dist[hit]
        ref_err = (self.pos - self._reference(self.t)).norm(dim=-1)
        dense = 0.5 * torch.exp(-(ref_err**2) / 0.25) - 0.05 * (action**2).sum(-1)
        terminated = self.pos.norm(dim=-1) > 2.5
        sparse -= 10.0 * terminated
        self.t += 1
        truncated = (self.t >= self.horizon) & ~terminated
        final = self._obs()
        info = {"keyframe_crossed": crossed, "body_pos_error_w": err, "final_obs": final,
                "phase": self.t.float() / self.horizon, "joint_pos": self.pos.clone()}
        done = (terminated | truncated).nonzero().flatten()
        if len(done):
            self._reset(done)
        return self._obs(), {"sparse": sparse, "dense": dense}, terminated, truncated, info


def small_cfg(**over) -> TrainConfig:
    raw = {"ppo": {"num_envs": 64, "steps_per_iteration": 16, "epochs": 4, "minibatches": 4, "learning_rate": 3e-3},
           "network": {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "adapter_hidden": [16], "init_log_std": -0.5},
           "save_interval": 5}
    raw.update(over)
    return TrainConfig.from_dict(raw)


def make_stage1(env, cfg, seed=0):
    torch.manual_seed(seed)
    net = cfg.network
    policy = Stage1Policy(env.actor_obs_dim, env.action_dim, net.actor_hidden, net.activation, net.init_log_std,
                          phase_rate=env.dphi)
    critic = DoubleCritic(env.critic_obs_dim, net.critic_hidden, net.activation)
    return policy, critic


META = {"robot": "toy", "joint_names": ["x", "y"], "action_dim": 2, "actor_obs_dim": 3, "critic_obs_dim": 4,
        "obs_layout": {"pos": 2, "phase": 1}, "phase_rate": 1.0 / 16, "stage": 1, "variant": "adamimic",
        "architecture": {"actor_hidden": [32, 32], "critic_hidden": [32, 32], "adapter_hidden": [16],
                         "activation": "elu", "adaptive_phase": False, "freeze_base": True, "normalize_obs": True}}


@torch.no_grad()
def evaluate(policy, episodes_envs: int = 256) -> float:
    """Mean undiscounted return (sparse + dense) of the deterministic policy over one episode."""
    torch.manual_seed(123)
    env = ToyKeyframeEnv(episodes_envs)
    obs = env.reset()
    total = torch.zeros(episodes_envs)
    alive = torch.ones(episodes_envs, dtype=torch.bool)
    for _ in range(env.horizon):
        action, _ = policy(obs["actor"])
        obs, rew, term, trunc, _ = env.step(action)
        total += alive * (rew["sparse"] + rew["dense"])
        alive &= ~(term | trunc)
    return total.mean().item()
