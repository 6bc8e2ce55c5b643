"""The training stages' command line: --chunk-minutes reaches the trainer, and an unfinished chunk exits
with EXIT_PAUSED so that a shell loop of `--resume` calls knows to go on."""

import pytest

from pipeline import stages
from pipeline.cli import EXIT_PAUSED, stage_main


@pytest.fixture
def trainer_calls(monkeypatch):
    """Stage 1 stands in: it records its keyword arguments and answers paused or finished."""
    calls, answers = [], []

    def fake_train_stage1(data, env_cfg, cfg, run_dir, go_states=None, handoff=None, **kwargs):
        assert go_states is None  # the sample's params start no episode at the go (env.go_starts.prob 0)
        assert handoff is None  # nor pay at a handoff (env.rewards.weights.handoff_catch 0)
        calls.append(kwargs)
        return answers.pop(0)

    import pipeline.rl.training as trainer

    monkeypatch.setattr(trainer, "train_stage1", fake_train_stage1)
    monkeypatch.setattr(stages, "_tracking_data", lambda params, task, variant: None)
    return calls, answers


def test_chunk_minutes_reaches_the_trainer_and_a_paused_chunk_exits_75(trainer_calls, capsys):
    calls, answers = trainer_calls
    answers += [{"paused": True, "iteration": 7}, {"iterations": 280}]
    argv = ["--task", "far_jump_sample", "--variant", "adamimic", "--chunk-minutes", "0.5"]
    with pytest.raises(SystemExit) as paused:
        stage_main(stages.run_train_stage1, argv=argv)
    assert paused.value.code == EXIT_PAUSED == 75
    assert calls[-1] == {"resume": False, "chunk_s": 30.0}
    assert "--resume" in capsys.readouterr().err

    stage_main(stages.run_train_stage1, argv=argv + ["--resume"])  # the last chunk finishes: no exit
    assert calls[-1] == {"resume": True, "chunk_s": 30.0}
    assert '"iterations": 280' in capsys.readouterr().out


def test_without_chunk_minutes_the_run_is_not_chunked(trainer_calls):
    calls, answers = trainer_calls
    answers.append({"iterations": 280})
    stage_main(stages.run_train_stage1, argv=["--task", "far_jump_sample", "--variant", "adamimic"])
    assert calls == [{"resume": False, "chunk_s": None}]


def test_a_task_paid_at_its_handoff_trains_with_its_chains_handoff_and_catcher():
    """far_jump_rest's recipe paid with the catch: the handoff at its landing keyframe, judged by balance.out's
    training checkpoint; unpaid (as committed), no handoff to train to."""
    from pathlib import Path
    from types import SimpleNamespace

    from pipeline.config import load_params

    folder = Path(__file__).resolve().parent.parent / "models/pretrained/far_jump_rest"
    params = load_params(folder / "params_cpu.yaml")
    data = SimpleNamespace(task="far_jump_rest", motion=SimpleNamespace(num_frames=126, fps=50.0),
                           keyframe_frames=[60, 85, 110], keyframe_labels=("takeoff", "landing", ""))
    assert stages._handoff(params, "far_jump_rest", data) is None
    params.env.rewards.weights.handoff_catch = 300.0
    handoff = stages._handoff(params, "far_jump_rest", data)
    assert handoff.phase == pytest.approx(85 / 125)  # clip.handoff_after_landing_s: 0.0
    assert handoff.balance_checkpoint.resolve() == (folder.parent / "balance_far_jump/train/policy").resolve()
    assert (handoff.balance_checkpoint / "model.safetensors").is_file()
    assert stages._handoff(load_params(folder.parent.parent.parent / "params.yaml"), "far_jump_sample", data) is None


@pytest.mark.parametrize("minutes", ["0", "-2"])
def test_a_chunk_must_last(trainer_calls, capsys, minutes):
    with pytest.raises(SystemExit) as bad:
        stage_main(stages.run_train_stage1,
                   argv=["--task", "far_jump_sample", "--variant", "adamimic", "--chunk-minutes", minutes])
    assert bad.value.code == 2
    assert "--chunk-minutes: must be > 0" in capsys.readouterr().err
    assert trainer_calls[0] == []  # refused before training started


def test_train_seed_pauses_in_stage_2_and_resumes_without_retraining_stage_1(trainer_calls, monkeypatch, tmp_path):
    calls, answers = trainer_calls
    monkeypatch.setattr(stages.paths, "seed_model_dir", lambda task, variant, seed: tmp_path / str(seed))
    stage2 = []
    monkeypatch.setattr(stages, "_train_stage2_into",
                        lambda params, args, cfg, model_dir, resume=False, go_states=None:
                        stage2.append((cfg.seed, resume)) or stage2_answers.pop(0))
    stage2_answers = [{"paused": True}, {"iterations": 150}]
    answers.append({"iterations": 280})
    argv = ["--task", "far_jump_sample", "--variant", "adamimic", "--seed", "1", "--chunk-minutes", "1"]
    with pytest.raises(SystemExit) as paused:  # stage 1 done, the chunk ran out inside stage 2
        stage_main(stages.run_train_seed, argv=argv)
    assert paused.value.code == EXIT_PAUSED and len(calls) == 1 and stage2 == [(1, False)]

    finished = tmp_path / "1" / "stage1"  # what the finished stage 1 left
    (finished / "policy").mkdir(parents=True)
    (finished / "policy" / "config.json").write_text("{}")
    (finished / "metrics.json").write_text('{"iterations": 280}')
    stage_main(stages.run_train_seed, argv=argv + ["--resume"])
    assert len(calls) == 1, "a finished stage 1 must not be trained (or rewritten) again"
    assert stage2 == [(1, False), (1, True)]


def test_go_starts_record_the_chains_balance_policy_at_the_go():
    """With env.go_starts on, the training stages hand the trainer stands of params.yaml's balance.out."""
    import dataclasses
    from pathlib import Path

    from pipeline.config import load_params

    params = load_params(Path(__file__).resolve().parent.parent / "params.yaml")
    go = dataclasses.replace(params.env.go_starts, prob=0.5, stands=2, stand_s=0.4)
    params = dataclasses.replace(params, env=dataclasses.replace(params.env, go_starts=go))
    states = stages._go_states(params)
    assert states["qpos"].shape[1] == 34 and 1 <= len(states["qpos"]) <= 2
    assert abs(states["qpos"][0, 2]) < 0.05  # relative to the stance's root: a nominal stand stays near it


def test_train_seed_records_the_go_states_once_for_both_stages(monkeypatch, tmp_path):
    """Stage 1 and stage 2 of a seed run start at the same go states, recorded once (a few seconds of stands)."""
    recorded, seen = [], []
    monkeypatch.setattr(stages, "_go_states", lambda params: recorded.append(1) or {"qpos": "the stands"})
    monkeypatch.setattr(stages, "_tracking_data", lambda params, task, variant: None)
    monkeypatch.setattr(stages.paths, "seed_model_dir", lambda task, variant, seed: tmp_path / str(seed))
    import pipeline.rl.training as trainer

    monkeypatch.setattr(trainer, "train_stage1", lambda *a, go_states=None, **k: seen.append(go_states) or {})
    monkeypatch.setattr(trainer, "train_stage2", lambda *a, go_states=None, **k: seen.append(go_states) or {})
    stage_main(stages.run_train_seed, argv=["--task", "far_jump_sample", "--variant", "adamimic", "--seed", "1"])
    assert recorded == [1] and seen == [{"qpos": "the stands"}] * 2


def test_a_resumed_seed_run_with_nothing_left_to_train_records_no_go_states(monkeypatch, tmp_path):
    """Stage 1 done in an earlier chunk and a variant without stage 2: nothing starts at the go states, so no
    stands are run to record them; the one-stage copy is still made."""
    recorded = []
    monkeypatch.setattr(stages, "_go_states", lambda params: recorded.append(1) or {"qpos": "the stands"})
    monkeypatch.setattr(stages.paths, "seed_model_dir", lambda task, variant, seed: tmp_path / str(seed))
    stage1 = tmp_path / "1" / "stage1"
    (stage1 / "policy").mkdir(parents=True)
    (stage1 / "policy" / "config.json").write_text("{}")
    (stage1 / "metrics.json").write_text('{"success": 0.5}')
    stage_main(stages.run_train_seed, argv=["--task", "far_jump_sample", "--variant", "adamimic_stage1", "--seed", "1",
                                            "--resume"])
    assert recorded == []
    assert (tmp_path / "1" / "final" / "policy" / "config.json").is_file()
