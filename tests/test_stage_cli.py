"""The training stages' command line: --chunk-minutes reaches the trainer, and an unfinished chunk exits
with EXIT_PAUSED so that a shell loop of `--resume` calls knows to go on."""

import pytest

from pipeline import stages
from pipeline.cli import EXIT_PAUSED, stage_main


@pytest.fixture
def trainer_calls(monkeypatch):
    """Stage 1 stands in: it records its keyword arguments and answers paused or finished."""
    calls, answers = [], []

    def fake_train_stage1(data, env_cfg, cfg, run_dir, **kwargs):
        calls.append(kwargs)
        return answers.pop(0)

    import pipeline.rl.trainer as trainer

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


@pytest.mark.parametrize("minutes", ["0", "-2"])
def test_a_chunk_must_last(trainer_calls, capsys, minutes):
    with pytest.raises(SystemExit) as bad:
        stage_main(stages.run_train_stage1,
                   argv=["--task", "far_jump_sample", "--variant", "adamimic", "--chunk-minutes", minutes])
    assert bad.value.code == 2
    assert "--chunk-minutes: must be > 0" in capsys.readouterr().err
    assert trainer_calls[0] == []  # refused before training started
