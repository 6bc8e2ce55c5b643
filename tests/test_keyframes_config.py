"""Task declarations: the seven paper tasks load, a new task needs little, each bad input is refused."""

from pathlib import Path

import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.common.yaml_strict import load_yaml_strict
from pipeline.keyframes.config import TaskConfig, label_matches
from pipeline.keyframes.task_parsing import load_tasks, merge_ranges
from pipeline.keyframes.select import select_keyframes
from pipeline.keyframes.synthetic import Flight, synthetic_jump_motion

PAPER = Path(__file__).resolve().parents[1] / "pipeline/keyframes/paper_tasks.yaml"
MINIMAL = {"input": "data/inputs/x.npz", "edit": "x", "psi": {"raw": 1.1, "easy": [[0.7, 1.6]], "hard": [[0.2, 0.7], [1.6, 2.0]]}}


def _task(**changes):
    raw = {**MINIMAL, **changes}
    return TaskConfig.from_dict("t1", raw)


def test_paper_tasks_load_with_paper_ranges():
    tasks = load_tasks(load_yaml_strict(PAPER)["tasks"])
    assert set(tasks) == {"far_jump", "high_jump", "triple_jump", "jump_step_up", "jump_step_down",
                          "tennis_hit", "badminton_hit"}
    far = tasks["far_jump"]
    assert far.psi.raw == 1.1 and far.psi.easy == ((0.7, 1.6),) and far.psi.hard == ((0.2, 0.7), (1.6, 2.0))
    assert far.psi.train == ((0.2, 2.0),)  # easy ∪ hard, merged
    assert tasks["high_jump"].psi.train == ((0.05, 0.6),)
    assert tasks["triple_jump"].psi.train == ((1.2, 4.2),)
    assert tasks["jump_step_down"].edit.sign == -1.0 and tasks["jump_step_down"].terrain.kind == "step"
    assert tasks["badminton_hit"].psi.train == ((1.3, 2.5),) and tasks["badminton_hit"].edit.mode == "heading"
    assert tasks["tennis_hit"].edit.mode == "y" and tasks["tennis_hit"].edit.sign == -1.0
    assert tasks["high_jump"].edit.mode == "z_apex"
    if (PAPER.parents[3] / "shared").is_dir():  # CI and developers have ../shared beside the repo
        for name in ("far_jump", "high_jump", "jump_step_up", "jump_step_down", "tennis_hit"):
            tasks[name].input_path(PAPER.parents[2])  # the five shared inputs exist


def test_minimal_task_gets_defaults():
    t = _task()
    assert t.keyframes.mode == "auto" and t.keyframes.spacing == 0.3
    assert t.edit.keyframes == ("landing",) and t.edit.sign == 1.0
    assert t.large_scale == 50.0 and t.large_scale_keyframes is None
    assert t.terrain.kind == "flat" and t.num_samples >= 1
    assert TaskConfig.from_dict("t2", {**MINIMAL, "edit": "z_apex"}).edit.keyframes == ("apex",)


def test_push_prior_block_reads_every_key():
    from pipeline.priors.push_prior import PushPriorConfig

    assert _task().push_prior == PushPriorConfig() and not PushPriorConfig().enabled
    raw = {"enabled": True, "iterations": 80, "population": 128, "seed": 3, "knots": 20, "land_by_slack_s": 0.1}
    assert _task(push_prior=raw).push_prior == PushPriorConfig(**raw)


def test_selectors_and_ranges_helpers():
    assert label_matches("landing", "landing_2") and label_matches("landing", "landing")
    assert not label_matches("landing_2", "landing_1") and not label_matches("landing", "")
    assert merge_ranges([(1.6, 2.0), (0.2, 0.7), (0.7, 1.6)]) == ((0.2, 2.0),)


@pytest.mark.parametrize("changes, field, words", [
    ({"edit": "w"}, "edit.mode", "unknown edit axis"),
    ({"edit": {"mode": "x", "keyframes": []}}, "edit.keyframes", "non-empty"),
    ({"terrain": "lava"}, "terrain.kind", "unknown terrain"),
    ({"terrain": "step"}, "terrain.kind", "z_hold"),
    ({"psi": {"raw": 1.0, "easy": [[1.6, 0.7]]}}, "psi.easy[0]", "inverted"),
    ({"psi": {"raw": 1.0, "easy": [[0.7, 0.7]]}}, "psi.easy[0]", "empty"),
    ({"psi": {"raw": 1.0, "easy": []}}, "psi.easy", "empty"),
    ({"psi": {"raw": 1.0, "train": [[0.5, 1.0]], "hard": [[2.0, 1.0]]}}, "psi.hard[0]", "inverted"),
    ({"psi": {"easy": [[0.5, 1.0]]}}, "psi.raw", "missing"),
    ({"input": None}, "input", "path"),
    ({"num_samples": 0}, "num_samples", ">= 1"),
    ({"keyframes": [{"time": 1.0}, {"time": 0.5}]}, "keyframes", "increasing"),
    ({"keyframes": [{"time": 0.5, "label": "takeoff"}, {"time": 1.0}]}, "edit.keyframes", "does not exist"),
    ({"keyframes": [{"time": 0.5}], "edit": {"mode": "x", "keyframes": [0.7]}}, "edit.keyframes", "does not exist"),
    ({"push_prior": {"enabled": True, "knots": 1}}, "push_prior.knots", ">= 2"),
    ({"push_prior": {"enabled": True, "iterations": 0}}, "push_prior.iterations", ">= 1"),
    ({"push_prior": {"enabled": True, "land_by_slack_s": -0.1}}, "push_prior.land_by_slack_s", "[0, 0.5]"),
    ({"push_prior": {"enabled": True, "land_by_slack_s": "late"}}, "push_prior.land_by_slack_s", "seconds"),
    ({"clip": {"start_s": -1.0}}, "clip.start_s", ">= 0"),
    ({"clip": {"start_s": 2.0, "end_s": 1.5}}, "clip.end_s", "after clip.start_s"),
    ({"clip": {"from": 1.0}}, "clip", "unknown key"),
    ({"colour": "red"}, "", "unknown key"),
])
def test_bad_task_names_task_and_field(changes, field, words):
    with pytest.raises(PipelineInputError) as err:
        _task(**changes)
    assert err.value.source == "task t1"
    assert (err.value.field or "") == field
    assert words in err.value.problem


def test_duplicate_task_names_refused(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text("tasks:\n  far_jump: {input: a.npz}\n  other: {input: b.npz}\n  far_jump: {input: c.npz}\n")
    with pytest.raises(PipelineInputError) as err:
        load_yaml_strict(path)
    assert err.value.field == "far_jump" and "duplicate" in err.value.problem
    path.write_text("tasks:\n  a: {input: a.npz}\n  b: {input: b.npz}\n")
    assert set(load_yaml_strict(path)["tasks"]) == {"a", "b"}


def test_missing_input_named():
    with pytest.raises(PipelineInputError, match="input"):
        _task(input="data/inputs/nothing_here.npz").input_path()


@pytest.fixture(scope="module")
def jump():
    return synthetic_jump_motion([Flight(1.0, 0.4, 1.1)], duration=2.5)


def test_keyframe_beyond_motion_end(jump):
    task = _task(keyframes=[{"time": 0.5}, {"time": 1.4, "label": "landing"}, {"time": 3.0}])
    with pytest.raises(PipelineInputError) as err:
        select_keyframes(jump, task)
    assert err.value.source == "task t1" and "beyond the motion's end" in err.value.problem
    task = _task(keyframes={"overrides": {"landing": 2.9}})
    with pytest.raises(PipelineInputError, match="beyond"):
        select_keyframes(jump, task)


def test_edited_keyframe_missing_in_motion(jump):
    # A hit is requested but the motion has none of that label after overriding events.
    task = _task(keyframes={"events": ["takeoff"]})
    with pytest.raises(PipelineInputError) as err:
        select_keyframes(jump, task)
    assert err.value.field == "edit.keyframes" and "'landing' does not exist" in err.value.problem
    standing = synthetic_jump_motion([], duration=2.0)
    with pytest.raises(PipelineInputError, match="does not exist"):
        select_keyframes(standing, _task())


def test_the_far_jump_gpu_recipe_loads_and_points_at_the_shared_clip():
    """models/pretrained/far_jump/params.yaml: the gpu profile on the paper's far jump with its push prior,
    its input resolved from the file's own folder to ../shared beside the repository."""
    from pipeline.config import load_params

    root = Path(__file__).resolve().parents[1]
    params = load_params(root / "models/pretrained/far_jump/params.yaml")
    train = params.train
    assert (train.profile, train.backend, train.device, train.ppo.num_envs) == ("gpu", "warp", "cuda", 4096)
    assert train.time_limit_stage1_s > 0 and train.time_limit_stage2_s > 0
    task = params.tasks["far_jump"]
    assert (params.path.parent / task.input).resolve() == (root.parent / "shared/data/adamimic_smpl/far_jump.npz").resolve()
    assert task.psi.raw == 1.1 and task.terrain.kind == "gap"
    assert task.push_prior.enabled  # every CPU run that learnt the far jump trained on one


def test_clip_window_cuts_the_keyframes_stage_outputs(jump, tmp_path):
    """`clip` keeps the window's frames only: keyframes, D_edit and the table's times count from its start,
    and the table records where the window sits in the clip."""
    import json

    from pipeline.keyframes.datasets import load_tracking_data
    from pipeline.keyframes.outputs import build_task_outputs

    whole = build_task_outputs(jump, _task(), tmp_path / "whole", num_samples=2, seed=0, video=False)
    cut = build_task_outputs(jump, _task(clip={"start_s": 0.5, "end_s": 2.0}), tmp_path / "cut", num_samples=2,
                             seed=0, video=False)
    table, whole_table = (json.loads(Path(p["keyframes"]).read_text()) for p in (cut, whole))
    assert table["clip"] == {"start_s": 0.5, "end_s": 2.0, "frames": [25, 101]} and "clip" not in whole_table
    data = load_tracking_data(cut["d_edit"])
    assert data.motion.num_frames == 76
    assert data.motion.root_pos[0] == pytest.approx(jump.root_pos[25])
    takeoff = dict(zip(whole_table["labels"], whole_table["times"]))["takeoff"]
    assert dict(zip(table["labels"], table["times"]))["takeoff"] == pytest.approx(takeoff - 0.5, abs=0.03)


def test_clip_window_past_the_clip_end_is_refused_before_any_write(jump, tmp_path):
    from pipeline.keyframes.outputs import build_task_outputs

    with pytest.raises(PipelineInputError) as err:
        build_task_outputs(jump, _task(clip={"start_s": 1.0, "end_s": 3.0}), tmp_path / "out", num_samples=2,
                           video=False)
    assert err.value.source == "task t1" and err.value.field == "clip.end_s" and "2.50 s" in err.value.problem
    assert not (tmp_path / "out").exists()
