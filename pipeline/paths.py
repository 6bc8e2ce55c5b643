"""Where each stage reads and writes, in one place (dvc.yaml uses the same layout)."""

from __future__ import annotations

from pathlib import Path


def human_dir(task: str) -> Path:
    return Path("data/human") / task


def retarget_dir(task: str) -> Path:
    return Path("data/retargeted") / task


def keyframes_dir(task: str) -> Path:
    return Path("data/keyframes") / task


def push_prior_dir(task: str) -> Path:
    return Path("data/push_prior") / task


def model_dir(task: str, variant: str) -> Path:
    return Path("models") / task / variant


def seed_model_dir(task: str, variant: str, seed: int) -> Path:
    """An extra training seed's run (`extra_seeds` in params.yaml): its stage1/ and final/."""
    return model_dir(task, variant) / "seeds" / str(seed)


def seed_results_dir(task: str, variant: str, seed: int) -> Path:
    return results_dir(task, variant) / "seeds" / str(seed)


def results_dir(task: str, variant: str | None = None) -> Path:
    base = Path("results") / task
    return base / variant if variant else base


def report_dir(task: str) -> Path:
    return Path("reports") / task
