"""Replay buffer of many synchronous worlds, with n-step returns for two reward groups.

Every world steps at once, so the buffer is a ring of `capacity` steps by `num_envs` worlds, (C, N, ...):
slot t of world e follows slot t − 1 of the same world, and an n-step return walks forward along
one world's column, stopping at the first episode end. Each transition stores its own next
observation (the env's `final_obs` at an episode end), so a timeout bootstraps from the state it
reached, not from the next episode's first.

When the actor's observation is the first columns of the critic's (TrackingEnv's is), only the
critic's is stored: about half the memory.
"""

from __future__ import annotations

import torch

GROUPS = ("sparse", "dense")


class ReplayBuffer:
    def __init__(self, capacity: int, num_envs: int, critic_dim: int, action_dim: int, device,
                 actor_dim: int | None = None, actor_is_prefix: bool = True):
        self.capacity, self.num_envs, self.device = capacity, num_envs, device
        self.actor_dim, self.actor_is_prefix = actor_dim, actor_is_prefix

        def z(*shape, dtype=torch.float32):
            return torch.zeros(capacity, num_envs, *shape, dtype=dtype, device=device)

        self.data = {"critic_obs": z(critic_dim), "next_critic_obs": z(critic_dim), "actions": z(action_dim),
                     "rewards": z(len(GROUPS)), "terminated": z(dtype=torch.bool), "truncated": z(dtype=torch.bool)}
        if not actor_is_prefix:
            self.data["actor_obs"], self.data["next_actor_obs"] = z(actor_dim), z(actor_dim)
        self.ptr = 0   # the slot the next step goes to
        self.size = 0  # steps held (per world)

    def __len__(self) -> int:
        return self.size * self.num_envs

    def add(self, obs: dict, actions: torch.Tensor, rewards: dict, next_obs: dict,
            terminated: torch.Tensor, truncated: torch.Tensor) -> None:
        """One step of every world: obs/next_obs {"actor", "critic"} (N, D), rewards {group: (N,)}."""
        row = {"critic_obs": obs["critic"], "next_critic_obs": next_obs["critic"], "actions": actions,
               "rewards": torch.stack([rewards[g] for g in GROUPS], -1),
               "terminated": terminated.bool(), "truncated": truncated.bool()}
        if not self.actor_is_prefix:
            row["actor_obs"], row["next_actor_obs"] = obs["actor"], next_obs["actor"]
        for key, value in row.items():
            self.data[key][self.ptr] = value
        self.ptr = (self.ptr + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def _actor(self, critic_obs: torch.Tensor, key: str, slot, env) -> torch.Tensor:
        if self.actor_is_prefix:
            return critic_obs[:, : self.actor_dim]
        return self.data[key][slot, env]

    def sample(self, batch: int, n_step: int, gammas: dict[str, float], bootstrap_timeouts: dict[str, bool]) -> dict:
        """`batch` n-step transitions, uniformly over every (start step, world) whose n steps are held.

        Returns obs (actor, critic), actions, for each group the discounted reward sum over the steps
        up to the first episode end `returns[g]` and the factor its bootstrap value takes `discounts[g]`
        (γ^steps; 0 after a termination, and after a timeout for a group that does not bootstrap
        there), and the observation to bootstrap from (next_actor_obs, next_critic_obs)."""
        starts = self.size - n_step + 1
        if starts <= 0:
            raise RuntimeError(f"the replay buffer holds {self.size} steps, fewer than n_step = {n_step}")
        oldest = (self.ptr - self.size) % self.capacity
        t = (oldest + torch.randint(0, starts, (batch,), device=self.device)) % self.capacity
        env = torch.randint(0, self.num_envs, (batch,), device=self.device)
        d = self.data
        critic_obs = d["critic_obs"][t, env]
        out = {"actor_obs": self._actor(critic_obs, "actor_obs", t, env), "critic_obs": critic_obs,
               "actions": d["actions"][t, env]}
        returns = torch.zeros(batch, len(GROUPS), device=self.device)
        gamma = torch.tensor([gammas[g] for g in GROUPS], device=self.device)
        alive = torch.ones(batch, dtype=torch.bool, device=self.device)
        steps = torch.zeros(batch, device=self.device)
        last = t.clone()  # slot of the last step taken (its next observation is the bootstrap's)
        terminated = torch.zeros(batch, dtype=torch.bool, device=self.device)
        truncated = torch.zeros(batch, dtype=torch.bool, device=self.device)
        for j in range(n_step):
            slot = (t + j) % self.capacity
            returns += alive[:, None] * gamma**j * d["rewards"][slot, env]
            last = torch.where(alive, slot, last)
            steps += alive.float()
            terminated |= alive & d["terminated"][slot, env]
            truncated |= alive & d["truncated"][slot, env] & ~d["terminated"][slot, env]
            alive &= ~(d["terminated"][slot, env] | d["truncated"][slot, env])
        next_critic = d["next_critic_obs"][last, env]
        out["next_critic_obs"] = next_critic
        out["next_actor_obs"] = self._actor(next_critic, "next_actor_obs", last, env)
        out["returns"], out["discounts"] = {}, {}
        for i, g in enumerate(GROUPS):
            keep = ~terminated & (~truncated if not bootstrap_timeouts[g] else torch.ones_like(truncated))
            out["returns"][g] = returns[:, i]
            out["discounts"][g] = gamma[i] ** steps * keep.float()
        return out

    # -- state (checkpoints) ------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The held steps in ring order (oldest first), so a load needs no pointer arithmetic."""
        order = (self.ptr - self.size + torch.arange(self.size, device=self.device)) % self.capacity
        return {"size": self.size, "data": {k: v[order].cpu().clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        size = int(state["size"])
        if size > self.capacity or set(state["data"]) != set(self.data):
            raise ValueError(f"a replay buffer of {size} steps and fields {sorted(state['data'])} does not fit this one "
                             f"({self.capacity} steps, fields {sorted(self.data)})")
        for k, v in state["data"].items():
            if v.shape[1:] != self.data[k].shape[1:]:
                raise ValueError(f"replay buffer field {k}: shape {tuple(v.shape[1:])}, this run's {tuple(self.data[k].shape[1:])}")
            self.data[k][:size] = v.to(self.device)
        self.size, self.ptr = size, size % self.capacity
