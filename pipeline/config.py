"""`params.yaml` → one typed, validated `PipelineConfig`.

Each concern owns its section's dataclass (retarget, tasks, env, train, evaluate) and validates it
with errors that name the offending key; this module only composes them, rejects unknown top-level
keys and resolves the compute profile. Validation runs at the start of every stage, so a broken
edit stops `dvc repro` at its first stage with the key named.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.common.errors import PipelineInputError

PROFILES = ("cpu", "gpu")
PAPER_TASKS = Path(__file__).resolve().parent / "keyframes" / "paper_tasks.yaml"
TOP_LEVEL_KEYS = ("profile", "variants", "extra_seeds", "seed_variants", "retarget", "tasks", "env", "train", "evaluate",
                  "balance")


@dataclass
class PipelineConfig:
    path: Path
    profile: str
    variants: tuple[str, ...]
    retarget: Any  # pipeline.retarget.config.RetargetConfig
    tasks: dict[str, Any]  # name -> pipeline.keyframes.config.TaskConfig
    env: Any  # pipeline.envs.config.EnvConfig
    train: Any  # pipeline.rl.config.TrainConfig (profile already applied)
    evaluate: Any  # pipeline.evaluation.config.EvalConfig
    raw: dict
    # Training seeds beside train.seed: each trains stage 1 + 2 and is evaluated like the main policy,
    # and the report gives success over all of them (mean, spread).
    extra_seeds: tuple[int, ...] = ()
    # The variants the report gives over every training seed (all of `variants` unless the file names some):
    # a comparison of ten methods can spend its second seeds on the rows whose order decides a claim.
    # dvc.yaml trains every variant at each extra seed, so a DVC sweep seeds some rows only by setting
    # extra_seeds in their experiments alone.
    seed_variants: tuple[str, ...] = ()
    balance: Any = None  # pipeline.balance.config.BalanceConfig: the policy every task's chain stands with

    @property
    def seeds(self) -> tuple[int, ...]:
        """Every training seed the report aggregates: train.seed first, then extra_seeds."""
        return (self.train.seed, *self.extra_seeds)


def _section(raw: dict, key: str, path: Path) -> dict:
    value = raw.get(key, {})
    if value is None:
        value = {}
    if not isinstance(value, dict):
        raise PipelineInputError(path, key, f"must be a mapping, got {type(value).__name__}")
    return value


def paper_tasks() -> dict:
    """The seven tasks of the paper (inputs, keyframe labels, edits, psi ranges, terrain)."""
    from pipeline.common.yaml_strict import load_yaml_strict

    return load_yaml_strict(PAPER_TASKS)["tasks"]


def _deep_merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        out[key] = _deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def resolve_task_templates(tasks_raw: dict, path: Path) -> dict:
    """`extends: <paper task>` starts a task from the paper's declaration; its own keys override."""
    library = None
    resolved = {}
    for name, raw in tasks_raw.items():
        if not isinstance(raw, dict):
            raise PipelineInputError(path, f"tasks.{name}", "must be a mapping")
        if "extends" in raw:
            library = library if library is not None else paper_tasks()
            parent = raw["extends"]
            if parent not in library:
                raise PipelineInputError(path, f"tasks.{name}.extends",
                                         f"unknown paper task {parent!r}; known: {', '.join(library)}")
            if "input" not in raw:  # dvc.yaml's stages read `input` from params.yaml itself, not from here
                raise PipelineInputError(path, f"tasks.{name}.input",
                                         f"a task that extends {parent!r} names its clip too (dvc.yaml tracks it as a "
                                         f"dependency from params.yaml): add `input: {library[parent]['input']}` or "
                                         f"your own clip's path")
            raw = _deep_merge(library[parent], {k: v for k, v in raw.items() if k != "extends"})
        resolved[name] = raw
    return resolved


def load_params(path: str | Path = "params.yaml") -> PipelineConfig:
    from pipeline.balance.config import BalanceConfig
    from pipeline.envs.config import EnvConfig
    from pipeline.evaluation.config import EvalConfig
    from pipeline.common.yaml_strict import load_yaml_strict
    from pipeline.keyframes.task_parsing import load_tasks
    from pipeline.retarget.config import RetargetConfig
    from pipeline.rl.config import TrainConfig, get_variant

    path = Path(path)
    if not path.exists():
        raise PipelineInputError(path, None, "parameters file not found")
    raw = load_yaml_strict(path)
    if not isinstance(raw, dict):
        raise PipelineInputError(path, None, "must be a YAML mapping")
    unknown = sorted(set(raw) - set(TOP_LEVEL_KEYS))
    if unknown:
        raise PipelineInputError(path, unknown[0], f"unknown key (expected one of {', '.join(TOP_LEVEL_KEYS)})")

    profile = raw.get("profile", "cpu")
    if profile not in PROFILES:
        raise PipelineInputError(path, "profile", f"must be one of {PROFILES}, got {profile!r}")
    variants = raw.get("variants", ["adamimic"])
    if not isinstance(variants, list) or not variants:
        raise PipelineInputError(path, "variants", "must be a non-empty list of variant names")
    for i, name in enumerate(variants):
        get_variant(name, where=f"{path}: variants[{i}]")
    if len(set(variants)) != len(variants):
        raise PipelineInputError(path, "variants", "lists a variant twice")

    tasks_raw = _section(raw, "tasks", path)
    if not tasks_raw:
        raise PipelineInputError(path, "tasks", "declare at least one task")
    train = TrainConfig.from_dict({**_section(raw, "train", path), "profile": profile}, where="train")
    return PipelineConfig(
        path=path,
        profile=profile,
        variants=tuple(variants),
        retarget=RetargetConfig.from_dict(_section(raw, "retarget", path), where="retarget"),
        tasks=load_tasks(resolve_task_templates(tasks_raw, path)),
        env=EnvConfig.from_dict(_section(raw, "env", path), where="env"),
        train=train,
        evaluate=EvalConfig.from_dict(_section(raw, "evaluate", path), where="evaluate"),
        raw=raw,
        extra_seeds=_extra_seeds(raw.get("extra_seeds", []), train.seed, path),
        seed_variants=_seed_variants(raw.get("seed_variants", variants), variants, path),
        balance=BalanceConfig.from_dict(_section(raw, "balance", path), profile),
    )


def _extra_seeds(value, main_seed: int, path: Path) -> tuple[int, ...]:
    if value is None:
        return ()
    if not isinstance(value, list):
        raise PipelineInputError(path, "extra_seeds", f"must be a list of seeds, got {type(value).__name__}")
    for i, seed in enumerate(value):
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise PipelineInputError(path, f"extra_seeds[{i}]", f"must be an integer >= 0, got {seed!r}")
        if seed == main_seed:
            raise PipelineInputError(path, f"extra_seeds[{i}]", f"is train.seed ({main_seed}), which trains already")
    if len(set(value)) != len(value):
        raise PipelineInputError(path, "extra_seeds", "lists a seed twice")
    return tuple(value)


def _seed_variants(value, variants: list[str], path: Path) -> tuple[str, ...]:
    if not isinstance(value, list):
        raise PipelineInputError(path, "seed_variants", f"must be a list of variant names, got {type(value).__name__}")
    for i, name in enumerate(value):
        if name not in variants:
            raise PipelineInputError(path, f"seed_variants[{i}]", f"{name!r} is not one of variants {variants}")
    if len(set(value)) != len(value):
        raise PipelineInputError(path, "seed_variants", "lists a variant twice")
    return tuple(value)


def main(argv: list[str] | None = None) -> None:
    """`python -m pipeline.config [params.yaml]`: check the parameters before DVC reads them (`make repro`
    runs it), so a broken task is named by its key instead of by DVC's templating."""
    import sys

    argv = sys.argv[1:] if argv is None else argv
    path = argv[0] if argv else "params.yaml"
    try:
        params = load_params(path)
    except PipelineInputError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
    print(f"{path}: {len(params.tasks)} task(s), {len(params.variants)} variant(s)")


if __name__ == "__main__":
    main()
