"""`BalanceConfig`: params.yaml `balance:`, typed. The env's own numbers are `BalanceEnvConfig`'s; the
trainer's are the `train:` profile's (pipeline/rl/config.py) with `balance.train` on top."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pipeline.common.errors import PipelineInputError
from pipeline.envs.balance_config import BalanceEnvConfig
from pipeline.rl.config import TrainConfig

DEFAULT_OUT = "models/pretrained/balance"


@dataclass
class BalanceConfig:
    env: BalanceEnvConfig = field(default_factory=BalanceEnvConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    iterations: int = 1000
    time_limit_s: float = 0.0  # 0: none
    # the task policies' end-of-task states (`python -m pipeline.balance.starts`); "" or a missing file: stance starts only
    start_states: str = "data/balance/start_states.npz"
    out: str = DEFAULT_OUT  # where the trained policy, its export and its evaluation go
    eval_episodes: int = 1000  # the standing test: episodes of `eval_seconds` under randomisation and pushes
    eval_seconds: float = 10.0
    # a fine-tune: start from this checkpoint folder's networks and optimiser (e.g. the committed policy's
    # `train` run folder: its latest checkpoint) instead of from scratch; "" trains from scratch
    init_from: str = ""

    @classmethod
    def from_dict(cls, raw: dict | None, profile: str = "cpu", where: str = "balance") -> "BalanceConfig":
        raw = dict(raw or {})
        unknown = sorted(set(raw) - {"env", "train", "iterations", "time_limit_s", "start_states", "out",
                                     "eval_episodes", "eval_seconds", "init_from"})
        if unknown:
            raise PipelineInputError(where, unknown[0], "unknown key (expected env, train, iterations, time_limit_s, "
                                     "start_states, out, eval_episodes, eval_seconds, init_from)")
        env = BalanceEnvConfig.from_dict(raw.pop("env", None), where=f"{where}.env")
        train = TrainConfig.from_dict({**(raw.pop("train", None) or {}), "profile": profile}, where=f"{where}.train")
        cfg = cls(env=env, train=train, **raw)
        if isinstance(cfg.iterations, bool) or not isinstance(cfg.iterations, int) or cfg.iterations < 0:
            raise PipelineInputError(where, "iterations", f"must be an integer >= 0, got {cfg.iterations!r}")
        if cfg.iterations == 0 and not cfg.time_limit_s > 0:
            raise PipelineInputError(where, "iterations", "0 trains until time_limit_s: set it > 0")
        if cfg.eval_episodes < 1 or not cfg.eval_seconds > 0:
            raise PipelineInputError(where, "eval_episodes", "eval_episodes >= 1 and eval_seconds > 0")
        return cfg

    def start_states_path(self, root: Path) -> Path | None:
        return (root / self.start_states) if self.start_states else None
