"""Policies in hub format and resumable training checkpoints.

A policy folder holds `config.json` (robot, joints, observation layout and sizes, variant, stage,
architecture, normaliser statistics summary) and `model.safetensors` (tensors `policy.*` and, for
continuing training, `critic.*`). A training checkpoint is the same folder plus `training_state.pt`
(optimiser, iteration, RNG states, env state, running statistics).

Layout of a run:   <run>/checkpoints/iter_000050/{config.json, model.safetensors, training_state.pt}
                   <run>/checkpoints/latest         (name of the newest complete checkpoint)
                   <run>/policy/{config.json, model.safetensors}   (final)
Each checkpoint folder is written with `atomic_dir` and only then named in `latest`, so a kill -9
at any point leaves the previous checkpoint intact and loses at most one save interval.
"""

from __future__ import annotations

import json
import random
import shutil
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from pipeline.common.atomic import atomic_dir, atomic_file, write_text_atomic
from pipeline.common.errors import PipelineInputError
from pipeline.rl.networks import DoubleCritic, Stage1Policy
from pipeline.rl.stage2 import Stage2Policy

FORMAT = "adamimic-policy/1"
CONFIG_FILE, WEIGHTS_FILE, STATE_FILE = "config.json", "model.safetensors", "training_state.pt"


# ------------------------------------------------------------------------------------------ policy files
def _tensors(policy: torch.nn.Module, critic: torch.nn.Module | None) -> dict[str, torch.Tensor]:
    out = {f"policy.{k}": v.detach().cpu().contiguous().clone() for k, v in policy.state_dict().items()}
    if critic is not None:
        out.update({f"critic.{k}": v.detach().cpu().contiguous().clone() for k, v in critic.state_dict().items()})
    return out


def write_policy_files(folder: Path, policy, critic, meta: dict) -> None:
    """Writes config.json + model.safetensors into an existing (staging) folder."""
    meta = dict(meta, format=FORMAT, normalizer=_normalizer_summary(policy))
    (folder / CONFIG_FILE).write_text(json.dumps(meta, indent=2, default=_json_default))
    save_file(_tensors(policy, critic), str(folder / WEIGHTS_FILE))


def save_policy(path: str | Path, policy, critic, meta: dict) -> None:
    with atomic_dir(path) as staging:
        write_policy_files(staging, policy, critic, meta)


def _normalizer_summary(policy) -> dict:
    norm = getattr(policy, "normalizer", None)
    if norm is None:
        return {}
    return {"enabled": bool(norm.enabled), "count": float(norm.count), "eps": norm.eps, "clip": norm.clip,
            "note": "running mean/var are the tensors policy.normalizer.mean/var in model.safetensors"}


def _json_default(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, tuple):
        return list(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def read_meta(path: str | Path) -> dict:
    path = Path(path)
    cfg_file = path / CONFIG_FILE
    if not cfg_file.is_file() or not (path / WEIGHTS_FILE).is_file():
        raise PipelineInputError(path, None, f"not a policy folder (needs {CONFIG_FILE} and {WEIGHTS_FILE})")
    try:
        meta = json.loads(cfg_file.read_text())
    except json.JSONDecodeError as err:
        raise PipelineInputError(cfg_file, None, f"invalid JSON: {err}") from None
    if meta.get("format") != FORMAT:
        raise PipelineInputError(cfg_file, "format", f"expected {FORMAT!r}, got {meta.get('format')!r}")
    for key, value in _IMPLIED.items():
        meta.setdefault(key, value)
    return meta


def build_policy_from_meta(meta: dict):
    """An untrained policy module with the architecture recorded in `meta`."""
    arch = meta["architecture"]
    base = Stage1Policy(meta["actor_obs_dim"], meta["action_dim"], arch["actor_hidden"], arch["activation"],
                        adaptive_phase=arch.get("adaptive_phase", False), phase_rate=meta["phase_rate"],
                        normalize_obs=arch.get("normalize_obs", True), output_bound=arch.get("output_bound", 0.0))
    if int(meta["stage"]) == 1:
        return base
    return Stage2Policy(base, arch["adapter_hidden"], arch["activation"], freeze_base=arch.get("freeze_base", True),
                        phase_rate=meta["phase_rate"], normalize_obs=arch.get("normalize_obs", True))


def build_critic_from_meta(meta: dict) -> DoubleCritic:
    arch = meta["architecture"]
    return DoubleCritic(meta["critic_obs_dim"], arch["critic_hidden"], arch["activation"], arch.get("normalize_obs", True))


VALIDATED_KEYS = ("robot", "joint_names", "action_dim", "actor_obs_dim", "obs_layout", "action_offset", "push_prior")
# What a checkpoint written before a key existed meant by it.
_IMPLIED = {"action_offset": "default", "push_prior": False}


def check_compatible(meta: dict, expect: dict | None, source: str | Path) -> None:
    """Raises naming the first of robot / joints / observation layout / action offset / push prior
    that differs from `expect`."""
    for key in VALIDATED_KEYS:
        if expect is None or key not in expect or expect[key] is None:
            continue
        want = json.loads(json.dumps(expect[key], default=_json_default))
        have = meta.get(key)
        if have != want:
            raise PipelineInputError(source, key, f"checkpoint has {_short(have)}, this run needs {_short(want)}")


def _short(x) -> str:
    s = json.dumps(x, default=_json_default)
    return s if len(s) < 120 else s[:117] + "..."


def load_policy(path: str | Path, expect: dict | None = None, *, with_critic: bool = False):
    """Loads a hub-format policy folder (or a training checkpoint folder).

    `expect` (e.g. {"robot": "unitree_g1", "obs_layout": ..., "actor_obs_dim": 465}) is checked
    against config.json before any tensor is read. Returns (policy in eval mode, meta) or, with
    `with_critic`, (policy, critic, meta).
    """
    path = Path(path)
    meta = read_meta(path)
    check_compatible(meta, expect, path)
    tensors = load_file(str(path / WEIGHTS_FILE))
    policy = build_policy_from_meta(meta)
    policy.load_state_dict({k[7:]: v for k, v in tensors.items() if k.startswith("policy.")})
    policy.eval()
    if not with_critic:
        return policy, meta
    critic = build_critic_from_meta(meta)
    critic_state = {k[7:]: v for k, v in tensors.items() if k.startswith("critic.")}
    if critic_state:
        # Critics saved before value normalisation lack its statistics: they start fresh (identity).
        missing, unexpected = critic.load_state_dict(critic_state, strict=False)
        missing = [k for k in missing if not k.split(".")[0].endswith("_returns")]
        if missing or unexpected:
            raise PipelineInputError(path, "critic", f"weights do not match the critic (missing {missing[:3]}, unexpected {unexpected[:3]})")
    return policy, critic, meta


# ------------------------------------------------------------------------------------------ RNG
def rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# ------------------------------------------------------------------------------------------ checkpoints
class CheckpointManager:
    def __init__(self, run_dir: str | Path, keep: int = 2):
        self.root = Path(run_dir) / "checkpoints"
        self.keep = keep

    def latest(self) -> Path | None:
        pointer = self.root / "latest"
        if not pointer.is_file():
            return None
        path = self.root / pointer.read_text().strip()
        return path if (path / STATE_FILE).is_file() else None

    def clear(self) -> None:
        """Forget every checkpoint here (a new run starting in this folder)."""
        (self.root / "latest").unlink(missing_ok=True)
        for old in self.root.glob("iter_*"):
            shutil.rmtree(old, ignore_errors=True)

    def save(self, iteration: int, policy, critic, meta: dict, training_state: dict) -> Path:
        name = f"iter_{iteration:06d}"
        with atomic_dir(self.root / name) as staging:
            write_policy_files(staging, policy, critic, dict(meta, iteration=iteration))
            with atomic_file(staging / STATE_FILE) as handle:
                torch.save(dict(training_state, iteration=iteration), handle)
        write_text_atomic(self.root / "latest", name)
        self._prune(keep_name=name)
        return self.root / name

    def _prune(self, keep_name: str) -> None:
        done = sorted(p for p in self.root.glob("iter_*") if p.is_dir() and (p / STATE_FILE).is_file())
        for old in done[: max(0, len(done) - self.keep)]:
            if old.name != keep_name:
                shutil.rmtree(old, ignore_errors=True)

    @staticmethod
    def load_state(path: Path) -> dict:
        # Our own file (optimiser + numpy RNG state need full unpickling).
        return torch.load(path / STATE_FILE, map_location="cpu", weights_only=False)
