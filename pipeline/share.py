"""`adamimic share`: a dataset or policy folder → a Hugging Face hub-format folder (+ push).

The folder written is exactly what would be uploaded: the artifact's own files plus a README.md
card with hub metadata (YAML front matter). Pushing needs `huggingface_hub`, a network and a token;
without them the folder is still written and the command says how to push it later.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from pipeline.common.atomic import atomic_dir
from pipeline.common.errors import PipelineInputError


def artifact_kind(path: Path) -> str:
    if (path / "meta" / "info.json").exists():
        return "dataset"
    if (path / "config.json").exists() and (path / "model.safetensors").exists():
        return "policy"
    raise PipelineInputError(
        path, None, "is neither a LeRobot dataset (meta/info.json) nor a policy (config.json + model.safetensors)"
    )


def _dataset_card(path: Path) -> str:
    info = json.loads((path / "meta" / "info.json").read_text())
    features = "\n".join(f"| `{k}` | {v.get('dtype')} | {v.get('shape')} |" for k, v in info.get("features", {}).items())
    return f"""---
license: cc-by-nc-sa-4.0
task_categories: [robotics]
tags: [LeRobot, unitree-g1, motion-retargeting, adamimic]
configs:
- config_name: default
  data_files: data/*/*.parquet
---
# {path.name}

Reference motions for the Unitree G1 made by the AdaMimic pipeline, in the LeRobot v3.0 layout
(codebase_version {info.get('codebase_version')}): {info.get('total_episodes')} episode(s),
{info.get('total_frames')} frames at {info.get('fps')} fps.

| feature | dtype | shape |
| --- | --- | --- |
{features}

Check the licence of the human clip this was made from before sharing it; the paper's clips are
CC BY-NC-SA 4.0.
"""


def _policy_card(path: Path) -> str:
    config = json.loads((path / "config.json").read_text())
    metrics = {}
    for candidate in (path / "metrics.json", path.parent / "metrics.json"):
        if candidate.exists():
            metrics = json.loads(candidate.read_text())
            break
    lines = "\n".join(f"- {k}: {v}" for k, v in metrics.items() if not isinstance(v, (dict, list)))
    return f"""---
library_name: onnxruntime
license: bsd-3-clause
tags: [robotics, reinforcement-learning, unitree-g1, adamimic, motion-tracking]
pipeline_tag: reinforcement-learning
---
# {path.name}

An AdaMimic policy for the Unitree G1 (task `{config.get('task', '?')}`, variant `{config.get('variant', '?')}`).
`policy.onnx` takes the observation history and returns joint targets and the phase-rate offset;
`policy.json` holds joint order, PD gains, default pose, action scale, observation layout and the
psi range. `config.json` + `model.safetensors` hold the torch weights.

{lines or 'No metrics recorded beside this policy.'}
"""


def write_hub_folder(src: Path, out: Path) -> str:
    src, out = Path(src), Path(out)
    if not src.is_dir():
        raise PipelineInputError(src, None, "not a folder")
    kind = artifact_kind(src)
    with atomic_dir(out) as staging:
        shutil.copytree(src, staging, dirs_exist_ok=True, ignore=shutil.ignore_patterns("training_state*", "*.tmp"))
        card = _dataset_card(src) if kind == "dataset" else _policy_card(src)
        (staging / "README.md").write_text(card)
    return kind


def share(src: Path, out: Path, repo_id: str | None = None) -> str:
    kind = write_hub_folder(src, out)
    if repo_id is None:
        return f"wrote {kind} in hub format to {out} (give --repo-id to push it)"
    try:
        from huggingface_hub import HfApi
    except ImportError:
        return f"wrote {kind} to {out}; to push, `pip install huggingface_hub` and run again with --repo-id"
    api = HfApi()
    repo_type = "dataset" if kind == "dataset" else "model"
    try:
        api.create_repo(repo_id, repo_type=repo_type, exist_ok=True)
        api.upload_folder(folder_path=str(out), repo_id=repo_id, repo_type=repo_type)
    except Exception as error:  # network, auth: the folder is written either way
        return f"wrote {kind} to {out}; push to {repo_id} failed: {error}"
    return f"pushed {kind} {out} to {repo_id}"
