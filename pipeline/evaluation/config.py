"""`EvalConfig`: the `evaluate` section of params.yaml, typed and validated (errors name the key)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from pipeline.common.errors import PipelineInputError
from pipeline.envs.falls import SUCCESS_THRESHOLD_M


@dataclass(frozen=True)
class VideoConfig:
    width: int = 1280
    height: int = 720
    fps: int = 25  # every 2nd control step of 50 Hz: real time, half the rendering cost
    per_range: int = 1  # videos per ψ range when `psi` is not given (spread inside the range)
    psi: tuple[float, ...] = ()  # explicit ψ values; empty = `per_range` values per range
    max_seconds: float = 12.0  # a video stops here (a chain: 2 s standing, the task, 3 s after it)


@dataclass(frozen=True)
class EvalConfig:
    episodes_per_range: int = 64  # the paper used > 10 000; a CPU default that runs in minutes
    runs: int = 3  # mean ± std over runs with different seeds (equal unless randomisation or sampling is on)
    num_envs: int = 32
    seed: int = 0
    success_threshold_m: float = SUCCESS_THRESHOLD_M
    ranges: tuple[str, ...] = ("easy", "hard")
    psi_grid_points: int = 9  # plots vs ψ: uniform grid over the union of the ranges
    adapter_psi_points: int = 4  # ψ values in the adapters' behaviour figure
    domain_randomization: bool = False
    deterministic: bool = True
    # rest_to_rest: chains (stand → go → task → balance, export/chain.py) per range, nominal and under the
    # paper's domain randomisation (metrics_dr.json), at ψ spread evenly inside each range
    chain_episodes_per_range: int = 32
    backend: str = "cpu"
    device: str = "cpu"
    video: VideoConfig = field(default_factory=VideoConfig)

    @staticmethod
    def from_dict(raw: dict[str, Any] | None, where: str = "evaluate") -> "EvalConfig":
        raw = dict(raw or {})
        video_raw = raw.pop("video", None) or {}
        if not isinstance(video_raw, dict):
            raise PipelineInputError(where, "video", f"must be a mapping, got {type(video_raw).__name__}")
        values = _typed(EvalConfig, raw, where, skip={"video"})
        video = VideoConfig(**_typed(VideoConfig, dict(video_raw), f"{where}.video"))
        cfg = EvalConfig(**values, video=video)
        cfg.validate(where)
        return cfg

    def validate(self, where: str = "evaluate") -> None:
        positive = {
            "episodes_per_range": self.episodes_per_range, "runs": self.runs, "num_envs": self.num_envs,
            "chain_episodes_per_range": self.chain_episodes_per_range,
            "psi_grid_points": self.psi_grid_points,
            "adapter_psi_points": self.adapter_psi_points, "video.width": self.video.width,
            "video.height": self.video.height, "video.fps": self.video.fps,
        }
        for key, value in positive.items():
            if value <= 0:
                raise PipelineInputError(where, key, f"must be positive, got {value}")
        if self.success_threshold_m <= 0:
            raise PipelineInputError(where, "success_threshold_m", f"must be positive, got {self.success_threshold_m}")
        if self.video.per_range < 0:
            raise PipelineInputError(where, "video.per_range", f"must be >= 0, got {self.video.per_range}")
        if not self.ranges:
            raise PipelineInputError(where, "ranges", "needs at least one ψ range name")
        if self.backend not in ("cpu", "warp"):
            raise PipelineInputError(where, "backend", f"must be 'cpu' or 'warp', got {self.backend!r}")


def _typed(cls, raw: dict[str, Any], where: str, skip: set[str] = frozenset()) -> dict[str, Any]:
    """Checks keys and coerces scalar types against the dataclass' defaults."""
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in skip}
    unknown = sorted(set(raw) - set(fields))
    if unknown:
        raise PipelineInputError(where, unknown[0], f"unknown key; expected one of {sorted(fields)}")
    defaults = cls()
    out: dict[str, Any] = {}
    for key, value in raw.items():
        default = getattr(defaults, key)
        try:
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise TypeError
                out[key] = value
            elif isinstance(default, int):
                if isinstance(value, bool) or float(value) != int(value):
                    raise TypeError
                out[key] = int(value)
            elif isinstance(default, float):
                if isinstance(value, bool):
                    raise TypeError
                out[key] = float(value)
            elif isinstance(default, tuple):
                if not isinstance(value, (list, tuple)):
                    raise TypeError
                kind = type(default[0]) if default else float
                out[key] = tuple(kind(v) for v in value)
            else:
                out[key] = str(value)
        except (TypeError, ValueError):
            raise PipelineInputError(where, key, f"expected {type(default).__name__}, got {value!r}") from None
    return out
