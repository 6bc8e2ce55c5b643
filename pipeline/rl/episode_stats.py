"""Per-env episode figures for the training loop: returns, lengths and the paper's success."""

from __future__ import annotations

import numpy as np
import torch

from pipeline.envs.falls import SUCCESS_THRESHOLD_M
from pipeline.rl.ppo import GROUPS

SUCCESS_ERROR_M = SUCCESS_THRESHOLD_M  # an episode fails if the mean body error exceeds it at a keyframe
MAX_PENDING_STEPS = 256  # steps of finished-episode figures kept on the device before a read-back
class EpisodeStats:
    """Per-env returns and success flags; finished episodes go into a sliding window.

    A step only queues its finished episodes' figures on the device; they are read back in one copy
    when the window is read (`summary`, `state_dict`). Read per episode, they were dozens of
    device-to-host syncs a step at 4096 GPU worlds."""

    def __init__(self, num_envs: int, device, window: int = 200):
        self.returns = {g: torch.zeros(num_envs, device=device) for g in GROUPS}
        self.failed = torch.zeros(num_envs, dtype=torch.bool, device=device)
        self.steps = torch.zeros(num_envs, dtype=torch.long, device=device)
        self.window = window
        self._finished: list[dict] = []
        self._pending: list[tuple[list[str], torch.Tensor, torch.Tensor]] = []  # (columns, done (N,), values (N, C))

    def step(self, rewards, terminated, truncated, info) -> None:
        for g in GROUPS:
            self.returns[g] += rewards[g]
        crossed, err = info.get("keyframe_crossed"), info.get("body_pos_error_w")
        if crossed is not None and err is not None:
            self.failed |= crossed.bool() & (err.mean(-1) > SUCCESS_ERROR_M)
        self.failed |= terminated.bool()
        self.steps += 1
        done = terminated | truncated
        causes = info.get("terminated_by") or {}
        columns = ["success", "length", *GROUPS, *(f"ended_by_{name}" for name in causes)]
        figures = [(~self.failed).float(), self.steps.float(), *(self.returns[g] for g in GROUPS),
                   *((terminated & flags.bool()).float() for flags in causes.values())]
        catch = info.get("handoff_catch")  # what the balance policy made of the state handed over (NaN: none)
        if catch is not None:
            columns.append("handoff_catch")
            figures.append(catch.float())
        values = torch.stack(figures, dim=1)
        if self._pending and (self._pending[0][0] != columns or len(self._pending) >= MAX_PENDING_STEPS):
            self._flush()
        self._pending.append((columns, done, values))
        for g in GROUPS:
            self.returns[g] = torch.where(done, 0.0, self.returns[g])
        self.failed &= ~done
        self.steps = torch.where(done, 0, self.steps)

    @property
    def finished(self) -> list[dict]:
        """The last `window` finished episodes, oldest first."""
        self._flush()
        return self._finished

    def _flush(self) -> None:
        if self._pending:
            columns = self._pending[0][0]
            done = torch.cat([d for _, d, _ in self._pending])
            rows = torch.cat([v for _, _, v in self._pending])[done].tolist()  # one copy to the host
            self._finished.extend(dict(zip(columns, row)) for row in rows)
            self._pending.clear()
        self._finished = self._finished[-self.window :]

    def reset(self) -> None:
        for g in GROUPS:
            self.returns[g].zero_()
        self.failed.zero_()
        self.steps.zero_()

    def summary(self) -> dict[str, float]:
        finished = self.finished
        if not finished:
            return {}
        out = {"success_rate": float(np.mean([e["success"] for e in finished])),
               "return_sparse": float(np.mean([e["sparse"] for e in finished])),
               "return_dense": float(np.mean([e["dense"] for e in finished])),
               "episode_length": float(np.mean([e.get("length", np.nan) for e in finished])),
               "episodes": len(finished)}
        # share of finished episodes each termination check ended (diagnostics)
        for key in sorted({k for e in finished for k in e if k.startswith("ended_by_")}):
            out[key] = float(np.mean([e.get(key, 0.0) for e in finished]))
        handed = [e["handoff_catch"] for e in finished if not np.isnan(e.get("handoff_catch", np.nan))]
        if handed:  # the mean catch estimate of the episodes that reached the chain's handoff
            out["handoff_catch"] = float(np.mean(handed))
        return out

    def state_dict(self) -> dict:
        return {"returns": {g: v.clone() for g, v in self.returns.items()}, "failed": self.failed.clone(),
                "steps": self.steps.clone(), "finished": list(self.finished)}

    def load_state_dict(self, s: dict) -> None:
        for g in GROUPS:
            self.returns[g].copy_(s["returns"][g])
        self.failed.copy_(s["failed"])
        if "steps" in s:
            self.steps.copy_(s["steps"])
        self._finished, self._pending = list(s["finished"]), []
