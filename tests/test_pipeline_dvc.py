"""The pipeline as users drive it: params validation at the first stage, a new task added in
params.yaml only and built by `dvc repro`, caching (second repro does nothing, a task's change
reruns only that task), a DVC remote round trip, and an experiment run from DVC's queue.

The end-to-end test runs on a copy of the repository with tiny training/evaluation sizes, so it
checks the plumbing (every stage of a new task runs and is cached), not the learning.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline import REPO_ROOT
from pipeline.common.errors import PipelineInputError
from pipeline.config import load_params

SHARED_FAR_JUMP = REPO_ROOT.parent / "shared" / "data" / "adamimic_smpl" / "far_jump.npz"
VENV_BIN = Path(sys.executable).parent


def _write_params(path: Path, edit) -> Path:
    raw = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    edit(raw)
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}"  # stages run `python`
    env["MUJOCO_GL"] = "egl"
    env.pop("PYTHONPATH", None)
    return env


# --------------------------------------------------------------------------- validation
def test_default_params_validate():
    params = load_params(REPO_ROOT / "params.yaml")
    assert params.profile == "cpu"
    assert "far_jump_sample" in params.tasks
    assert params.tasks["far_jump_sample"].edit.mode == "x"  # inherited from the paper's far_jump


@pytest.mark.parametrize(
    "edit, key",
    [
        (lambda r: r.update(profil="cpu"), "profil"),
        (lambda r: r.update(profile="tpu"), "profile"),
        (lambda r: r.update(variants=["adamimic", "nope"]), "variants[1]"),
        (lambda r: r["tasks"]["far_jump_sample"].update(extends="long_jump"), "tasks.far_jump_sample.extends"),
        (lambda r: r["tasks"]["far_jump_sample"]["psi"].update(easy=[[0.9, 0.3]]), "psi"),
        (lambda r: r["train"].update(iterations_stage1=-3), "iterations_stage1"),
        (lambda r: r["train"].update(iterations_stage2=0, time_limit_stage2_s=0), "iterations_stage2"),
        (lambda r: r["train"].update(time_limit_stage2_s=-5), "time_limit_stage2_s"),
        (lambda r: r["env"]["rewards"]["weights"].update(global_body_poss=1.0), "global_body_poss"),
        (lambda r: r["retarget"].update(solver="ikpy"), "solver"),
    ],
)
def test_bad_params_name_the_key(tmp_path, edit, key):
    path = _write_params(tmp_path / "params.yaml", edit)
    with pytest.raises(PipelineInputError) as error:
        load_params(path)
    assert key in str(error.value)


def test_bad_params_stop_the_first_stage_with_the_key(tmp_path):
    path = _write_params(tmp_path / "params.yaml", lambda r: r["train"].update(ppo={"clip": "wide"}))
    result = subprocess.run(
        [sys.executable, "stages/import_motion.py", "--params", str(path), "--task", "far_jump_sample"],
        cwd=REPO_ROOT, capture_output=True, text=True, env=_env(),
    )
    assert result.returncode == 2
    assert "clip" in result.stderr and "Traceback" not in result.stderr


def test_missing_input_is_named_with_its_task(tmp_path):
    out = tmp_path / "human"

    def edit(raw):
        raw["tasks"]["triple"] = {"extends": "triple_jump", "input": str(tmp_path / "missing.npz")}

    path = _write_params(tmp_path / "params.yaml", edit)
    result = subprocess.run(
        [sys.executable, "stages/import_motion.py", "--params", str(path), "--task", "triple"],
        cwd=REPO_ROOT, capture_output=True, text=True, env=_env(),
    )
    assert result.returncode == 2
    assert "task triple" in result.stderr and "input" in result.stderr and "missing.npz" in result.stderr
    assert not out.exists()


def test_a_task_extending_a_paper_task_without_its_input_is_named_before_dvc_runs(tmp_path):
    """`tasks: {triple_jump: {extends: triple_jump}}`: DVC's templating would fail on `item.input` with its own
    words; the project's check (`python -m pipeline.config`, the first step of `make repro`) names the task and
    the key and says what to write, and a task that writes it parses."""
    path = _write_params(tmp_path / "params.yaml", lambda r: r["tasks"].update(triple_jump={"extends": "triple_jump"}))
    result = subprocess.run([sys.executable, "-m", "pipeline.config", str(path)], cwd=REPO_ROOT, capture_output=True,
                            text=True, env=_env())
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "tasks.triple_jump.input" in result.stderr and "input: data/inputs/triple_jump.npz" in result.stderr
    fixed = _write_params(tmp_path / "fixed.yaml", lambda r: r["tasks"].update(
        triple_jump={"extends": "triple_jump", "input": "data/inputs/triple_jump.npz"}))
    result = subprocess.run([sys.executable, "-m", "pipeline.config", str(fixed)], cwd=REPO_ROOT, capture_output=True,
                            text=True, env=_env())
    assert result.returncode == 0 and "2 task(s)" in result.stdout
    assert "python -m pipeline.config params.yaml && dvc repro" in (REPO_ROOT / "Makefile").read_text()


def test_duplicate_task_names_are_refused(tmp_path):
    text = (REPO_ROOT / "params.yaml").read_text().replace(
        "tasks:\n", "tasks:\n  far_jump_sample:\n    extends: far_jump\n    input: x.npz\n", 1
    )
    path = tmp_path / "params.yaml"
    path.write_text(text)
    with pytest.raises(PipelineInputError) as error:
        load_params(path)
    assert "far_jump_sample" in str(error.value)


# --------------------------------------------------------------------------- end to end
def _copy_repo(dst: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO_ROOT, capture_output=True, check=True).stdout
    for rel in filter(None, files.decode().split("\0")):
        src = REPO_ROOT / rel
        if src.is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / rel)
    # The robot assets are fetched at set-up (not tracked): share them.
    (dst / "robots/g1/vendor").symlink_to(REPO_ROOT / "robots/g1/vendor")
    for cmd in (["git", "init", "-q"], ["git", "add", "-A"],
                ["git", "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-qm", "copy"]):
        subprocess.run(cmd, cwd=dst, check=True, capture_output=True)


def _dvc(repo: Path, *args: str) -> str:
    result = subprocess.run([sys.executable, "-m", "dvc", *args], cwd=repo, capture_output=True, text=True,
                            env=_env())
    assert result.returncode == 0, f"dvc {' '.join(args)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result.stdout + result.stderr


def _tiny(raw: dict) -> None:
    """Sizes that exercise every stage in seconds."""
    raw["train"].update(iterations_stage1=1, iterations_stage2=1, ppo={"num_envs": 8, "steps_per_iteration": 8})
    raw["evaluate"].update(episodes_per_range=2, runs=1, num_envs=2,
                           video={"per_range": 1, "max_seconds": 1.0, "width": 320, "height": 180})


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_FAR_JUMP.exists(), reason="needs ../shared/data/adamimic_smpl/far_jump.npz")
def test_new_task_in_params_runs_through_dvc_repro(tmp_path):
    repo = tmp_path / "repo"
    _copy_repo(repo)

    def add_task(raw):
        _tiny(raw)
        raw["extra_seeds"] = []  # one seed here: test_extra_seeds_train_evaluate_and_reach_the_report covers more
        raw["tasks"]["my_far_jump"] = {"extends": "far_jump", "input": str(SHARED_FAR_JUMP), "num_samples": 4}

    _write_params(repo / "params.yaml", add_task)
    targets = ["export@my_far_jump-adamimic", "report@my_far_jump"]
    log = _dvc(repo, "repro", *targets)
    for stage in ("import@my_far_jump", "retarget@my_far_jump", "keyframes@my_far_jump", "push_prior@my_far_jump",
                  "train_stage1@my_far_jump-adamimic", "train_stage2@my_far_jump-adamimic",
                  "evaluate@my_far_jump-adamimic", "export@my_far_jump-adamimic", "report@my_far_jump"):
        assert f"Running stage '{stage}'" in log, stage
    assert "far_jump_sample" not in log  # the other task was not touched
    for artifact in ("data/keyframes/my_far_jump/d_edit/meta/info.json",
                     "data/push_prior/my_far_jump/push_prior.json",
                     "models/my_far_jump/adamimic/final/policy/model.safetensors",
                     "models/my_far_jump/adamimic/export/policy.onnx",
                     "results/my_far_jump/adamimic/metrics.json",
                     "reports/my_far_jump/table.md"):
        assert (repo / artifact).is_file(), artifact

    # A second repro does nothing.
    assert "Running stage" not in _dvc(repo, "repro", *targets)

    # Editing one task's keyframe parameters invalidates that task from `keyframes` on, and only it.
    def more_samples(raw):
        raw["tasks"]["my_far_jump"]["num_samples"] = 5

    _write_params(repo / "params.yaml", lambda raw: (add_task(raw), more_samples(raw)))
    status = _dvc(repo, "status", "--with-deps", *targets)
    assert "keyframes@my_far_jump" in status
    assert "retarget@my_far_jump" not in status and "import@my_far_jump" not in status

    # Editing another task leaves this one up to date.
    _write_params(repo / "params.yaml", lambda raw: (add_task(raw), more_samples(raw),
                                                     raw["tasks"]["far_jump_sample"].update(num_samples=7)))
    _dvc(repo, "repro", *targets)
    assert "up to date" in _dvc(repo, "status", "--with-deps", *targets)

    # A DVC remote (a local folder) round-trips datasets and policies.
    remote = tmp_path / "remote"
    _dvc(repo, "remote", "add", "-d", "local", str(remote))
    _dvc(repo, "push", "--with-deps", *targets)
    policy = repo / "models/my_far_jump/adamimic/export/policy.onnx"
    original = policy.read_bytes()
    shutil.rmtree(repo / "models")
    shutil.rmtree(repo / "data/keyframes")
    shutil.rmtree(repo / ".dvc/cache")
    _dvc(repo, "pull", "--with-deps", *targets)
    assert policy.read_bytes() == original
    assert (repo / "data/keyframes/my_far_jump/d_edit/meta/info.json").is_file()


@pytest.mark.slow
def test_extra_seeds_train_evaluate_and_reach_the_report(tmp_path):
    """`extra_seeds` adds train_seed/evaluate_seed stages per seed beside the main run, whose paths stay
    as they were, and the report aggregates success over every seed (bundled sample, tiny sizes)."""
    repo = tmp_path / "repo"
    _copy_repo(repo)

    def tiny_seeds(raw, seeds=(3,)):
        _tiny(raw)
        raw["tasks"]["far_jump_sample"]["num_samples"] = 4
        raw["extra_seeds"] = list(seeds)

    _write_params(repo / "params.yaml", tiny_seeds)
    target = "report@far_jump_sample"
    log = _dvc(repo, "repro", target)
    for stage in ("train_stage1@far_jump_sample-adamimic", "evaluate@far_jump_sample-adamimic",
                  "train_seed@far_jump_sample-adamimic-3", "evaluate_seed@far_jump_sample-adamimic-3", target):
        assert f"Running stage '{stage}'" in log, stage
    for artifact in ("models/far_jump_sample/adamimic/final/policy/model.safetensors",
                     "results/far_jump_sample/adamimic/metrics.json",
                     "models/far_jump_sample/adamimic/seeds/3/stage1/policy/model.safetensors",
                     "models/far_jump_sample/adamimic/seeds/3/final/policy/model.safetensors",
                     "results/far_jump_sample/adamimic/seeds/3/metrics.json"):
        assert (repo / artifact).is_file(), artifact
    assert not list((repo / "results/far_jump_sample/adamimic/seeds/3/media").glob("*.mp4"))  # no videos
    base = repo / "models/far_jump_sample/adamimic"  # another seed trained another policy
    assert (base / "stage1/policy/model.safetensors").read_bytes() != (base / "seeds/3/stage1/policy/model.safetensors").read_bytes()

    summary = json.loads((repo / "reports/far_jump_sample/seeds.json").read_text())["adamimic"]
    assert summary["seeds"] == [0, 3]
    main = json.loads((repo / "results/far_jump_sample/adamimic/metrics.json").read_text())
    seed3 = json.loads((repo / "results/far_jump_sample/adamimic/seeds/3/metrics.json").read_text())
    assert summary["ranges"]["overall"]["success_per_seed"] == {
        "0": main["ranges"]["overall"]["success"]["mean"], "3": seed3["ranges"]["overall"]["success"]["mean"]}
    assert "## Success over training seeds (2: 0, 3)" in (repo / "reports/far_jump_sample/table.md").read_text()
    assert "Running stage" not in _dvc(repo, "repro", target)

    # One more seed: only its stages and the report are out of date, not the main run's training.
    _write_params(repo / "params.yaml", lambda raw: tiny_seeds(raw, seeds=(3, 5)))
    status = _dvc(repo, "status", "--with-deps", target)
    assert "train_seed@far_jump_sample-adamimic-5" in status and target in status
    assert "train_stage1@" not in status and "train_seed@far_jump_sample-adamimic-3" not in status


def _experiments(node, found=None) -> dict:
    """{experiment name: its metrics files} from `dvc exp show --json`, at any depth of its tree."""
    found = {} if found is None else found
    if isinstance(node, list):
        for item in node:
            _experiments(item, found)
    elif isinstance(node, dict):
        data = node.get("data")
        if node.get("name") and isinstance(data, dict) and data.get("metrics"):
            found[node["name"]] = data["metrics"]
        for key in ("experiments", "revs"):
            _experiments(node.get(key), found)
    return found


@pytest.mark.slow
def test_a_variant_runs_from_the_dvc_queue(tmp_path):
    """A sweep's experiment as a user queues it (the README's `-S 'variants=choice(…)'` queues one per variant),
    run by `dvc queue start` in DVC's own clean copy of the repository: the robot model, fetched at set-up and
    not tracked, goes in with `--copy-paths`; the experiment evaluates its variant (bundled sample, tiny sizes).
    One experiment, not two: each costs minutes of the suite."""
    import time

    repo = tmp_path / "repo"
    _copy_repo(repo)
    _write_params(repo / "params.yaml", lambda raw: (_tiny(raw), raw.update(extra_seeds=[]),
                                                     raw["tasks"]["far_jump_sample"].update(num_samples=4)))
    log = _dvc(repo, "exp", "run", "--queue", "--copy-paths", "robots/g1/vendor", "-S", "variants=[deepmimic_adapt]",
               "report@far_jump_sample")
    assert log.count("Queued experiment") == 1
    _dvc(repo, "queue", "start", "-j", "1")
    deadline = time.monotonic() + 1200
    while True:
        status = _dvc(repo, "queue", "status")
        if not any(word in status for word in ("Queued", "Running")):
            break
        assert time.monotonic() < deadline, status
        time.sleep(5)
    assert status.count("Success") == 1, status

    runs = _experiments(json.loads(_dvc(repo, "exp", "show", "--json")))
    queued = [name for name, metrics in runs.items() if "results/far_jump_sample/deepmimic_adapt/metrics.json" in metrics]
    assert len(queued) == 1, sorted(runs)
