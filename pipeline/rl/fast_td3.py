"""Off-policy stage-1 trainer in the FastTD3 style, written to be read top to bottom (`train.algorithm: fast_td3`).

The recipe recent humanoid whole-body-tracking work reports as several times faster than PPO per
sample: many parallel worlds feed one large replay buffer; large batches; clipped double Q; n-step
targets; running-normalised observations; a deterministic actor explored with Gaussian noise whose
std each world draws anew at every episode start (a mix of careful and bold worlds).

AdaMimic's two reward groups stay apart, as in the double-critic PPO (ppo.py):
  * sparse (keyframe rewards, termination): γ = 1, the episode's remaining sparse return; a timeout is
    the true end of the task, so nothing is bootstrapped past it;
  * dense (tracking every step): γ = 0.99; bootstrapped at timeouts from the state reached only with
    `bootstrap_dense_timeouts` (off by default: TrackingEnv's timeout is the clip's end, a state whose
    Q no transition ever trains).
Each group has its own output head on the twin Q networks (and their targets); each head regresses
    y_g = scale_g · R_g^(n) + discount_g · min(Q'_g1, Q'_g2)(s_n, π(s_n) + clipped noise),
R_g^(n) the group's n-step reward sum up to the first episode end (replay_buffer.py), scale_g a fixed
per-group reward scale that brings both groups' returns near unit size. The actor ascends
Σ_g w_g · Q_g(s, π(s)) (the twins' mean). Scaling each group's Q by its batch spread instead, as PPO
does its advantages, made the actor chase the noise of a nearly flat sparse critic early on.

The actor is a `networks.Stage1Policy` with a bounded mean (`output_bound`): policy files, export and
stage 2's adapters read it as any stage-1 policy (its mean is the deployed action).

Resume: a checkpoint holds the actor, the critics and their targets, both optimisers, the
exploration stds, the RNG states and (fast_td3.checkpoint_buffer, the default) the replay buffer, so
the resumed run's next update is bit-identical to the uninterrupted run's. Without the buffer, the
resumed run refills `learning_starts` steps of every world before it updates again.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import torch
from safetensors.torch import load_file
from torch import nn

from pipeline.common.errors import PipelineInputError
from pipeline.rl.checkpoint import WEIGHTS_FILE
from pipeline.rl.config import FastTD3Config, TrainConfig
from pipeline.rl.mirror import Mirror, mirror_for_env
from pipeline.rl.networks import EmpiricalNormalizer, Stage1Policy, mlp
from pipeline.rl.replay_buffer import GROUPS, ReplayBuffer
from pipeline.rl.trainer import Trainer
from pipeline.rl.training import pin_observation_stats, policy_meta


# ------------------------------------------------------------------------------------------ critics
class GroupCritic(nn.Module):
    """Twin Q networks on (normalised critic observation, raw action), each with one output head per
    reward group (column i: GROUPS[i]); one observation normaliser. Heads rather than a network per
    group: the update's cost is the critics' forward and backward passes, and on 2 cores it halves."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: list[int], activation: str = "elu", normalize_obs: bool = True):
        super().__init__()
        self.normalizer = EmpiricalNormalizer(obs_dim, enabled=normalize_obs)
        self.q1 = mlp(obs_dim + action_dim, hidden, len(GROUPS), activation)
        self.q2 = mlp(obs_dim + action_dim, hidden, len(GROUPS), activation)

    def forward(self, x: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(Q1, Q2), each (B, groups), on an already normalised observation x."""
        xa = torch.cat([x, action], -1)
        return self.q1(xa), self.q2(xa)

    def update_normalizers(self, obs: torch.Tensor) -> None:
        self.normalizer.update(obs)


# ------------------------------------------------------------------------------------------ the updates
class FastTD3:
    def __init__(self, actor: Stage1Policy, critic: GroupCritic, cfg: FastTD3Config, mirror: Mirror | None = None):
        self.actor, self.critic, self.cfg, self.mirror = actor, critic, cfg, mirror
        self.target = copy.deepcopy(critic).requires_grad_(False)
        # log_std is a Gaussian's: the deterministic actor explores with its own noise (see the trainer).
        self.actor_params = [p for name, p in actor.named_parameters() if name != "log_std" and p.requires_grad]
        self.actor_optimizer = torch.optim.AdamW(self.actor_params, lr=cfg.actor_learning_rate, weight_decay=cfg.weight_decay)
        self.critic_optimizer = torch.optim.AdamW(critic.parameters(), lr=cfg.critic_learning_rate, weight_decay=cfg.weight_decay)
        self.gammas = {"sparse": cfg.gamma_sparse, "dense": cfg.gamma_dense}
        self.scales = {"sparse": cfg.reward_scale_sparse, "dense": cfg.reward_scale_dense}
        self.weights = {"sparse": cfg.q_weight_sparse, "dense": cfg.q_weight_dense}
        self.bootstrap_timeouts = {"sparse": False, "dense": cfg.bootstrap_dense_timeouts}
        self.updates = 0

    @torch.no_grad()
    def explore(self, actor_obs: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
        """The actor's mean plus N(0, std²) per world (std: (N,)), kept inside the action bound."""
        mean = self.actor.raw_mean(actor_obs)
        noise = torch.randn_like(mean) * std[:, None]
        return (mean + noise).clamp(-self.cfg.action_bound, self.cfg.action_bound)

    def _mirror_half(self, batch: dict) -> dict:
        """Replays the second half of the batch mirrored left-right (mirror.py): same rewards, mirrored states."""
        half = batch["actions"].shape[0] // 2
        out = dict(batch)
        for key, kind in (("actor_obs", "actor"), ("next_actor_obs", "actor"), ("critic_obs", "critic"),
                          ("next_critic_obs", "critic"), ("actions", "raw")):
            x = batch[key]
            out[key] = torch.cat([x[:half], self.mirror.apply(kind, x[half:])])
        return out

    def update(self, batch: dict) -> dict[str, torch.Tensor]:
        """One critic step on every group's twins, then (every policy_delay-th) one actor step; then
        the target critics follow by Polyak averaging. Returns detached figures (on the device)."""
        cfg = self.cfg
        if self.mirror is not None:
            batch = self._mirror_half(batch)
        x = self.critic.normalizer(batch["critic_obs"])
        x_next = self.critic.normalizer(batch["next_critic_obs"])

        # -- critics: clipped double-Q n-step targets per group
        with torch.no_grad():
            next_mean = self.actor.raw_mean(batch["next_actor_obs"])
            smoothing = (torch.randn_like(next_mean) * cfg.target_noise).clamp(-cfg.target_noise_clip, cfg.target_noise_clip)
            next_action = (next_mean + smoothing).clamp(-cfg.action_bound, cfg.action_bound)
            next_q = torch.min(*self.target(x_next, next_action))  # (B, groups): clipped double Q per group
            target = torch.stack([self.scales[g] * batch["returns"][g] + batch["discounts"][g] * next_q[:, i]
                                  for i, g in enumerate(GROUPS)], -1)
        q1, q2 = self.critic(x, batch["actions"])
        # summed over the groups, averaged over the batch: each group's regression weighs alike
        critic_loss = ((q1 - target) ** 2).sum(-1).mean() + ((q2 - target) ** 2).sum(-1).mean()
        q_now = {g: q1[:, i].detach() for i, g in enumerate(GROUPS)}
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        if cfg.max_grad_norm > 0:
            nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
        self.critic_optimizer.step()
        stats = {"critic_loss": critic_loss.detach(), "q_sparse": q_now["sparse"].mean() / self.scales["sparse"],
                 "q_dense": q_now["dense"].mean() / self.scales["dense"]}

        # -- actor: ascend the groups' weighted Q (the twins' mean)
        self.updates += 1
        if self.updates % cfg.policy_delay == 0:
            self.critic.requires_grad_(False)  # the gradient flows through the critics to the action, not into them
            q1, q2 = self.critic(x, self.actor.raw_mean(batch["actor_obs"]))
            q = 0.5 * (q1 + q2)
            actor_loss = -sum(self.weights[g] * q[:, i].mean() for i, g in enumerate(GROUPS))
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.critic.requires_grad_(True)
            if cfg.max_grad_norm > 0:
                nn.utils.clip_grad_norm_(self.actor_params, cfg.max_grad_norm)
            self.actor_optimizer.step()
            stats["actor_loss"] = actor_loss.detach()

        # -- target critics
        with torch.no_grad():
            for slow, online in zip(self.target.parameters(), self.critic.parameters()):
                slow.lerp_(online, cfg.tau)
        return stats

    def state_dict(self) -> dict:
        return {"target": self.target.state_dict(), "actor_optimizer": self.actor_optimizer.state_dict(),
                "critic_optimizer": self.critic_optimizer.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.target.load_state_dict(state["target"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.updates = int(state["updates"])


# ------------------------------------------------------------------------------------------ the loop
class FastTD3Trainer(Trainer):
    """The shared loop (trainer.Trainer.run: curricula, logs, checkpoints, time caps across resumes)
    with an off-policy iteration: `steps_per_iteration` env steps of every world, each stored and
    followed by `updates_per_step` updates once the buffer holds `learning_starts` steps."""

    def _setup_algorithm(self, l2c2: bool) -> None:
        cfg = self.cfg.fast_td3
        self.algorithm = "fast_td3"
        self.steps_per_iteration = cfg.steps_per_iteration
        mirror = mirror_for_env(self.env, self.policy.raw_dim).to(self.device) if cfg.mirror else None
        self.td3 = FastTD3(self.policy, self.critic, cfg, mirror)
        n = self.spec.num_envs
        actor_dim, critic_dim = self.spec.actor_obs_dim, self.spec.critic_obs_dim
        # TrackingEnv's critic observation starts with the actor's (trainer's obs_layout: critic_privileged after it)
        self.buffer = ReplayBuffer(max(cfg.buffer_size // n, cfg.learning_starts + 1), n, critic_dim, self.policy.raw_dim,
                                   self.device, actor_dim=actor_dim, actor_is_prefix=self._actor_is_prefix())
        self.explore_std = torch.zeros(n, device=self.device)
        self._draw_explore_std(torch.ones(n, dtype=torch.bool, device=self.device))

    def _actor_is_prefix(self) -> bool:
        layout = self.spec.obs_layout
        if isinstance(layout, dict) and "critic_privileged" in layout:
            return all(start >= self.spec.actor_obs_dim for start, _ in layout["critic_privileged"].values())
        return False

    def _draw_explore_std(self, worlds: torch.Tensor) -> None:
        cfg = self.cfg.fast_td3
        fresh = cfg.exploration_std_min + (cfg.exploration_std_max - cfg.exploration_std_min) * torch.rand_like(self.explore_std)
        self.explore_std = torch.where(worlds, fresh, self.explore_std)

    def _boundary(self, iteration: int, obs: dict | None) -> dict:
        fresh = obs is None or (not self.spec.resumable and iteration % self.cfg.save_interval == 0)
        obs = super()._boundary(iteration, obs)
        if fresh:  # every world starts a new episode
            self._draw_explore_std(torch.ones_like(self.explore_std, dtype=torch.bool))
        return obs

    def _iteration(self, obs: dict) -> tuple[dict, dict]:
        cfg = self.cfg.fast_td3
        seen_actor, seen_critic, rewards_seen = [], [], {g: 0.0 for g in GROUPS}
        sums: dict[str, torch.Tensor] = {}
        counts: dict[str, int] = {}
        collect_seconds = update_seconds = 0.0
        for _ in range(self.steps_per_iteration):
            start = time.perf_counter()
            raw = self.td3.explore(obs["actor"], self.explore_std)
            with torch.no_grad():
                action, phase_offset = self.policy.to_env(obs["actor"], raw)
            next_obs, rewards, terminated, truncated, info = self.env.step(action, phase_offset if self.use_phase_offset else None)
            terminated, truncated = terminated.bool(), truncated.bool()
            self.stats.step(rewards, terminated, truncated, info)
            # the state each action reached: the env's final_obs where an episode ended (before its reset)
            reached = info.get("final_obs") or next_obs
            self.buffer.add(obs, raw, rewards, reached, terminated, truncated)
            self._draw_explore_std(terminated | truncated)
            seen_actor.append(obs["actor"])
            seen_critic.append(obs["critic"])
            for g in GROUPS:
                rewards_seen[g] += rewards[g].mean()
            obs = next_obs
            self._sync()
            middle = time.perf_counter()
            if self.buffer.size >= cfg.learning_starts:
                for _ in range(cfg.updates_per_step):
                    batch = self.buffer.sample(cfg.batch_size, cfg.n_step, self.td3.gammas, self.td3.bootstrap_timeouts)
                    for k, v in self.td3.update(batch).items():
                        sums[k] = sums.get(k, 0.0) + v.double()
                        counts[k] = counts.get(k, 0) + 1
            self._sync()
            collect_seconds += middle - start
            update_seconds += time.perf_counter() - middle
        # the normalisers move between iterations, like PPO's (after the iteration's updates)
        self.policy.update_normalizers(torch.stack(seen_actor))
        self.critic.update_normalizers(torch.stack(seen_critic))
        stats = {k: float(sums[k]) / counts[k] for k in sums}
        stats.update({"collect_seconds": collect_seconds, "update_seconds": update_seconds,
                      "reward_sparse": float(rewards_seen["sparse"]) / self.steps_per_iteration,
                      "reward_dense": float(rewards_seen["dense"]) / self.steps_per_iteration,
                      "action_std": float(self.explore_std.mean()), "buffer_transitions": len(self.buffer)})
        return stats, obs

    # -- saving / resuming ------------------------------------------------------------------
    def _algorithm_state(self) -> dict:
        state = {"fast_td3": self.td3.state_dict(), "explore_std": self.explore_std.clone()}
        if self.cfg.fast_td3.checkpoint_buffer:
            state["replay_buffer"] = self.buffer.state_dict()
        return state

    def _load_algorithm_state(self, state: dict, path: Path) -> None:
        self.td3.load_state_dict(state["fast_td3"])
        self.explore_std.copy_(state["explore_std"])
        if "replay_buffer" in state:
            try:
                self.buffer.load_state_dict(state["replay_buffer"])
            except ValueError as err:
                raise PipelineInputError(path, "replay_buffer", str(err)) from None
        else:
            self.log(f"[train] {path.name} holds no replay buffer (fast_td3.checkpoint_buffer: false): the resumed "
                     f"run refills {self.cfg.fast_td3.learning_starts} steps of every world before updating")

    def _load_critic(self, path: Path) -> None:
        tensors = load_file(str(path / WEIGHTS_FILE))
        state = {k[len("critic."):]: v for k, v in tensors.items() if k.startswith("critic.")}
        missing, unexpected = self.critic.load_state_dict(state, strict=False)
        if missing or unexpected:
            raise PipelineInputError(path, "critic", f"weights do not match the fast_td3 critics (missing {missing[:3]}, "
                                     f"unexpected {unexpected[:3]})")


def build_fast_td3_trainer(env, data, cfg: TrainConfig, run_dir, phase_rate: float, **trainer_kwargs) -> FastTD3Trainer:
    """Stage 1's actor (a Stage1Policy with a bounded mean), the group critics and the trainer."""
    variant, net, td3 = cfg.variant_spec, cfg.network, cfg.fast_td3
    if variant.amp != "none":  # the config refuses this pairing too; a variant set per run (stages.py) lands here
        raise PipelineInputError("train", "algorithm", f"variant {cfg.variant!r} (AMP) trains with ppo only, not fast_td3")
    policy = Stage1Policy(env.spec().actor_obs_dim, env.spec().action_dim, net.actor_hidden, net.activation, net.init_log_std,
                          adaptive_phase=variant.adaptive_phase_stage1, phase_rate=phase_rate,
                          normalize_obs=cfg.ppo.normalize_obs, output_bound=td3.action_bound)
    critic = GroupCritic(env.spec().critic_obs_dim, policy.raw_dim, net.critic_hidden, net.activation, cfg.ppo.normalize_obs)
    pin_observation_stats(env, [policy.normalizer, critic.normalizer])
    meta = policy_meta(env, data, cfg, 1, phase_rate, output_bound=td3.action_bound)
    return FastTD3Trainer(env, policy, critic, cfg, run_dir, stage=1, meta=meta,
                          use_phase_offset=variant.adaptive_phase_stage1, **trainer_kwargs)
