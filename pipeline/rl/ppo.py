"""Double-critic PPO, written to be read top to bottom.

AdaMimic splits rewards into two groups with different natures:
  * sparse: paid only on keyframe-crossing steps (plus termination); discount γ = 1.0, and a timeout
    is a true end of the task, so nothing is bootstrapped there;
  * dense: paid every step (local tracking, regularisers); γ = 0.99, and a timeout only cuts an
    episode that would go on, so the value of the state reached at the timeout is bootstrapped.
Each group has its own value network and its own GAE(λ); the two advantages are normalised
separately and combined as A = w_sparse·Â_sparse + w_dense·Â_dense before the usual clipped surrogate.

The policy is any module with `sample(obs)`, `log_prob_entropy(obs, raw)`, `raw_mean(obs)`,
`to_env(obs, raw)` and `update_normalizers(obs)` (stage 1: `networks.Stage1Policy`, stage 2:
`stage2.Stage2Policy`); the critic is a `networks.DoubleCritic`.
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import torch
from torch import nn

from pipeline.rl.config import PPOConfig

GROUPS = ("sparse", "dense")


# ------------------------------------------------------------------------------------------ GAE
def gae(rewards: torch.Tensor, values: torch.Tensor, last_values: torch.Tensor,
        terminated: torch.Tensor, truncated: torch.Tensor, gamma: float, lam: float,
        timeout_values: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimation for one reward group over a rollout of T steps.

    rewards, values, terminated, truncated: (T, N); last_values: (N,) value of the state after the
    rollout's last step. `timeout_values` (T, N): value of the state reached on a truncated step;
    given, it is bootstrapped (r + γ·V) at timeouts; None, a timeout ends the return like a termination.
    Returns (advantages, returns), both (T, N).
    """
    steps = rewards.shape[0]
    ended = (terminated | truncated).float()
    if timeout_values is not None:
        timeout_only = (truncated & ~terminated).float()
        rewards = rewards + gamma * timeout_values * timeout_only
    advantages = torch.zeros_like(rewards)
    running = torch.zeros_like(last_values)
    for t in reversed(range(steps)):
        next_values = last_values if t == steps - 1 else values[t + 1]
        not_ended = 1.0 - ended[t]
        delta = rewards[t] + gamma * next_values * not_ended - values[t]
        running = delta + gamma * lam * not_ended * running
        advantages[t] = running
    return advantages, advantages + values


def normalise(x: torch.Tensor) -> torch.Tensor:
    return (x - x.mean()) / (x.std() + 1e-8)


# ------------------------------------------------------------------------------------------ rollout
@dataclass
class Rollout:
    """One iteration of experience, every field (T, N, ...)."""

    actor_obs: torch.Tensor
    critic_obs: torch.Tensor
    raw_actions: torch.Tensor
    log_probs: torch.Tensor
    means: torch.Tensor
    stds: torch.Tensor
    values: dict[str, torch.Tensor]
    rewards: dict[str, torch.Tensor]
    terminated: torch.Tensor
    truncated: torch.Tensor
    timeout_values: dict[str, torch.Tensor]
    last_values: dict[str, torch.Tensor]

    @classmethod
    def allocate(cls, steps: int, num_envs: int, actor_dim: int, critic_dim: int, raw_dim: int, device) -> "Rollout":
        def z(*shape, dtype=torch.float32):
            return torch.zeros(steps, num_envs, *shape, dtype=dtype, device=device)

        return cls(
            actor_obs=z(actor_dim), critic_obs=z(critic_dim), raw_actions=z(raw_dim), log_probs=z(),
            means=z(raw_dim), stds=z(raw_dim),
            values={g: z() for g in GROUPS}, rewards={g: z() for g in GROUPS},
            terminated=z(dtype=torch.bool), truncated=z(dtype=torch.bool),
            timeout_values={g: z() for g in GROUPS},
            last_values={g: torch.zeros(num_envs, device=device) for g in GROUPS},
        )


# ------------------------------------------------------------------------------------------ PPO
class PPO:
    def __init__(self, policy: nn.Module, critic: nn.Module, cfg: PPOConfig, *, l2c2: bool = False):
        self.policy, self.critic, self.cfg, self.l2c2 = policy, critic, cfg, l2c2
        self.learning_rate = cfg.learning_rate
        self.actor_params = [p for p in policy.parameters() if p.requires_grad]
        self.critic_params = [p for p in critic.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(self.actor_params + self.critic_params, lr=self.learning_rate)
        self.gammas = {"sparse": cfg.gamma_sparse, "dense": cfg.gamma_dense}
        self.weights = {"sparse": cfg.adv_weight_sparse, "dense": cfg.adv_weight_dense}
        # Only the dense group bootstraps at timeouts (see the module docstring).
        self.bootstrap_timeouts = {"sparse": False, "dense": True}

    # -- acting -----------------------------------------------------------------------------
    @torch.no_grad()
    def act(self, actor_obs: torch.Tensor, critic_obs: torch.Tensor,
            noise: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Samples an action; returns what the rollout stores and what the env receives.
        The observation normalisers stay fixed during a rollout and its update (they move after
        the update, in `update`), so the stored means/log-probs match what the update recomputes.
        `noise`: the standard-normal ε to explore with (time-correlated, see exploration.py); None draws it."""
        raw, log_prob = self.policy.sample(actor_obs, noise)
        _, _, mean, std = self.policy.log_prob_entropy(actor_obs, raw)
        action, phase_offset = self.policy.to_env(actor_obs, raw)
        v_sparse, v_dense = self.critic(critic_obs)
        return {"raw": raw, "log_prob": log_prob, "mean": mean, "std": std, "action": action,
                "phase_offset": phase_offset, "sparse": v_sparse, "dense": v_dense}

    @torch.no_grad()
    def values(self, critic_obs: torch.Tensor) -> dict[str, torch.Tensor]:
        v_sparse, v_dense = self.critic(critic_obs)
        return {"sparse": v_sparse, "dense": v_dense}

    # -- advantages -------------------------------------------------------------------------
    def advantages(self, rollout: Rollout) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Per-group GAE, per-group normalisation, weighted sum. Returns (advantage, returns per group)."""
        combined = torch.zeros_like(rollout.log_probs)
        returns = {}
        for g in GROUPS:
            adv, ret = gae(
                rollout.rewards[g], rollout.values[g], rollout.last_values[g],
                rollout.terminated, rollout.truncated, self.gammas[g], self.cfg.lam,
                rollout.timeout_values[g] if self.bootstrap_timeouts[g] else None,
            )
            combined += self.weights[g] * normalise(adv)
            returns[g] = ret
        return combined, returns

    # -- the update -------------------------------------------------------------------------
    def update(self, rollout: Rollout) -> dict[str, float]:
        cfg = self.cfg
        advantages, returns = self.advantages(rollout)
        steps, num_envs = rollout.log_probs.shape
        total = steps * num_envs

        def flat(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(total, *x.shape[2:])

        obs_a, obs_c, raw = flat(rollout.actor_obs), flat(rollout.critic_obs), flat(rollout.raw_actions)
        old_log_prob, old_mean, old_std = flat(rollout.log_probs), flat(rollout.means), flat(rollout.stds)
        adv = flat(advantages)
        # Each critic head regresses its group's returns in units of that group's running return
        # statistics (DoubleCritic), refreshed with this rollout's returns first.
        norms = {g: self.critic.return_normalizer(g) for g in GROUPS}
        for g in GROUPS:
            norms[g].update(returns[g])
        ret = {g: norms[g].normalize(flat(returns[g])) for g in GROUPS}
        old_v = {g: norms[g].normalize(flat(rollout.values[g])) for g in GROUPS}
        # L2C2 pairs an observation with the next one of the same episode (flat index + num_envs).
        ended = flat(rollout.terminated | rollout.truncated)
        has_next = ~ended & (torch.arange(total, device=ended.device) < total - num_envs)

        stats = {k: torch.zeros((), dtype=torch.float64, device=adv.device)
                 for k in ("policy_loss", "value_loss_sparse", "value_loss_dense", "entropy", "kl", "l2c2", "clip_frac",
                           "grad_norm_actor", "grad_norm_critic")}
        updates = 0
        batch = total // cfg.minibatches
        for _ in range(cfg.epochs):
            order = torch.randperm(total, device=adv.device)
            for start in range(0, batch * cfg.minibatches, batch):
                idx = order[start : start + batch]
                log_prob, entropy, mean, std = self.policy.log_prob_entropy(obs_a[idx], raw[idx])

                # Adaptive learning rate from the exact KL between the old and new Gaussians.
                with torch.no_grad():
                    kl = (torch.log(std / old_std[idx]) + (old_std[idx] ** 2 + (old_mean[idx] - mean) ** 2)
                          / (2.0 * std**2) - 0.5).sum(-1).mean()
                    if cfg.adaptive_lr:
                        if kl > 2.0 * cfg.kl_target:
                            self.learning_rate = max(cfg.lr_min, self.learning_rate / 1.5)
                        elif 0.0 < kl < 0.5 * cfg.kl_target:
                            self.learning_rate = min(cfg.lr_max, self.learning_rate * 1.5)
                        for group in self.optimizer.param_groups:
                            group["lr"] = self.learning_rate

                # Clipped surrogate on the combined advantage.
                ratio = torch.exp(log_prob - old_log_prob[idx])
                surrogate = torch.min(ratio * adv[idx], ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv[idx])
                policy_loss = -surrogate.mean()

                # One regression per critic on its own group's returns.
                values = dict(zip(GROUPS, self.critic.normalized(obs_c[idx])))
                value_losses = {}
                for g in GROUPS:
                    err = (values[g] - ret[g][idx]) ** 2
                    if cfg.value_clip:
                        clipped = old_v[g][idx] + (values[g] - old_v[g][idx]).clamp(-cfg.clip, cfg.clip)
                        err = torch.max(err, (clipped - ret[g][idx]) ** 2)
                    value_losses[g] = err.mean()

                loss = (policy_loss + cfg.value_coef * (value_losses["sparse"] + value_losses["dense"])
                        - cfg.entropy_coef * entropy.mean())

                l2c2_loss = torch.zeros((), device=loss.device)
                if self.l2c2:
                    l2c2_loss = self._l2c2(idx, obs_a, obs_c, has_next, num_envs, mean, values)
                    loss = loss + l2c2_loss

                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                # Actor and critics clipped apart: one joint norm would let the critics' gradients
                # (value losses of O(1e4) before value normalisation) scale the actor's by ~1e-4.
                grad_actor = nn.utils.clip_grad_norm_(self.actor_params, cfg.max_grad_norm)
                grad_critic = nn.utils.clip_grad_norm_(self.critic_params, cfg.max_grad_norm)
                self.optimizer.step()

                updates += 1
                # summed on the device and read once after the epochs: an .item() here would wait
                # for each minibatch's backward pass on a GPU
                minibatch = {"policy_loss": policy_loss, "value_loss_sparse": value_losses["sparse"],
                             "value_loss_dense": value_losses["dense"], "entropy": entropy.mean(), "kl": kl,
                             "l2c2": l2c2_loss, "clip_frac": ((ratio - 1).abs() > cfg.clip).float().mean(),
                             "grad_norm_actor": grad_actor, "grad_norm_critic": grad_critic}
                for k, v in minibatch.items():
                    stats[k] += v.detach().double()
        self.policy.update_normalizers(rollout.actor_obs)
        self.critic.update_normalizers(rollout.critic_obs)
        totals = torch.stack(list(stats.values())).tolist()
        out = {k: v / max(updates, 1) for k, v in zip(stats, totals)}
        out["learning_rate"] = self.learning_rate
        out["action_std"] = float(old_std.mean())
        for g in GROUPS:
            out[f"return_std_{g}"] = float(norms[g].std)
        return out

    def _l2c2(self, idx, obs_a, obs_c, has_next, num_envs, mean, values) -> torch.Tensor:
        """L2C2: outputs at an observation and at a random point towards the next observation of the
        same episode should agree (a local Lipschitz-like constraint that smooths the policy)."""
        sel = has_next[idx]
        if self.cfg.l2c2_fraction < 1.0:  # idx is a slice of a random permutation: its head is a random subset
            head = math.ceil(self.cfg.l2c2_fraction * idx.numel())
            sel = sel & (torch.arange(idx.numel(), device=idx.device) < head)
        keep = idx[sel]
        if keep.numel() == 0:
            return torch.zeros((), device=mean.device)
        u = torch.rand(keep.shape[0], 1, device=mean.device)
        mid_a = obs_a[keep] + u * (obs_a[keep + num_envs] - obs_a[keep])
        mid_c = obs_c[keep] + u * (obs_c[keep + num_envs] - obs_c[keep])
        actor_term = ((self.policy.raw_mean(mid_a) - mean[sel]) ** 2).sum(-1).mean()
        v_mid = self.critic.normalized(mid_c)  # unit-scale outputs, as in the value loss
        critic_term = sum(((v_mid[i] - values[g][sel]) ** 2).mean() for i, g in enumerate(GROUPS))
        return self.cfg.l2c2_actor * actor_term + self.cfg.l2c2_critic * critic_term

    # -- state ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict(), "learning_rate": self.learning_rate}

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state["optimizer"])
        self.learning_rate = float(state["learning_rate"])
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate
