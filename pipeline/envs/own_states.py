"""A ring of per-world states the policy reached itself, to restart episodes from
(`EnvConfig.own_state_starts`).

Each entry is one world's slice of the env buffers named in `FIELDS` (physics state, ψ sample,
phase, observation history, ...), copied when that world crossed a chosen keyframe. A reset draws
entries uniformly. The ring lives on the env's device and is part of the env's `state_dict`, so a
resumed run draws the same restarts.
"""

from __future__ import annotations

import torch

from pipeline.common.errors import PipelineInputError

# What a restart restores: enough for the next step to be the one the recorded world would have taken
# (up to the per-world domain randomisation, which stays the new episode's own).
FIELDS = ("qpos", "qvel", "sample", "phase", "frame", "next_kf", "prev_action", "prev_action2", "prev_joint_vel",
          "obs_history", "privileged", "odometry", "odom_origin", "odom_origin_quat")


class OwnStateRing:
    def __init__(self, capacity: int, device="cpu"):
        self.capacity = int(capacity)
        self.device = torch.device(device)
        self.entries: dict[str, torch.Tensor] = {}  # allocated at the first `add`, shaped by it
        self.count = 0  # entries filled so far (<= capacity)
        self.next_slot = 0

    def __len__(self) -> int:
        return self.count

    def add(self, states: dict[str, torch.Tensor]) -> None:
        """Stores the rows of `states` (one per world, every name in FIELDS), overwriting the oldest."""
        rows = int(states["qpos"].shape[0])
        if rows == 0:
            return
        if rows > self.capacity:  # more crossings in one step than the ring holds: keep the last ones
            states = {name: value[-self.capacity:] for name, value in states.items()}
            rows = self.capacity
        if not self.entries:
            self.entries = {name: torch.zeros((self.capacity, *states[name].shape[1:]), dtype=states[name].dtype,
                                              device=self.device) for name in FIELDS}
        slots = (self.next_slot + torch.arange(rows, device=self.device)) % self.capacity
        for name in FIELDS:
            self.entries[name][slots] = states[name].to(self.device, self.entries[name].dtype)
        self.next_slot = (self.next_slot + rows) % self.capacity
        self.count = min(self.count + rows, self.capacity)

    def draw(self, n: int) -> dict[str, torch.Tensor]:
        """`n` entries drawn uniformly with replacement (torch's global RNG); the ring must not be empty."""
        pick = torch.randint(self.count, (n,), device=self.device)
        return {name: value[pick] for name, value in self.entries.items()}

    def state_dict(self) -> dict:
        return {"capacity": self.capacity, "count": self.count, "next_slot": self.next_slot,
                "entries": {name: value.detach().cpu().clone() for name, value in self.entries.items()}}

    def load_state_dict(self, state: dict) -> None:
        if int(state["capacity"]) != self.capacity:
            raise PipelineInputError("env state", "own_states.capacity",
                                     f"checkpoint has {state['capacity']}, this env {self.capacity}")
        self.count, self.next_slot = int(state["count"]), int(state["next_slot"])
        self.entries = {name: value.to(self.device).clone() for name, value in state["entries"].items()}
