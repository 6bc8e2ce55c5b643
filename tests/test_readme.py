"""The README and the docs/ pages name only things that exist (what is checked: tests/page_checker.py), and every
user-facing page dates its figures by day or commit."""

from __future__ import annotations

import re

import pytest

from page_checker import KEY, PAGES, ROOT, looks_like_path, page_problems, split_page


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_command_path_and_key_a_page_names_exists(page, monkeypatch, capsys):
    assert page_problems(page.read_text(), monkeypatch, capsys, base=page.parent) == []


def test_the_readme_is_checked_for_real():
    """The checks above find what they are meant to in the README (so an empty problem list means something)."""
    spans, links, commands, yamls = split_page((ROOT / "README.md").read_text())
    assert any(c.split()[0].endswith("adamimic") for c in commands)
    assert any("tasks:" in y for y in yamls)
    assert any(s.startswith("make ") for s in spans) and any(c.startswith("make ") for c in commands)
    assert any(KEY.match(s) for s in spans)
    assert any(looks_like_path(s) for s in spans) and any(l.startswith("benchmarks/RESULTS.md#") for l in links)


MADE_UP = """
Run `adamimic fly` or `adamimic play --colour red`, then `make deploy-to-mars`.
Set `env.rewards.sigma2.feet_position` or `train.ppo.learning_rate_of_doom`; see `pipeline/nowhere/thing.py`
and [the record](benchmarks/RESULTS.md#no-such-chapter).

```bash
.venv/bin/adamimic sim2sim models/far_jump_sample/adamimic/export --psi 0.4 --made-up-flag
.venv/bin/adamimic play models/far_jump_sample/adamimic/export --psi far
.venv/bin/python benchmarks/learn_cpu.py --segment 2.3 --no-such-option
.venv/bin/python stages/train_stage1.py --task T --fast
.venv/bin/python -m pipeline.evaluation.no_such_module
dvc exp run -S train.iterations_stage3=10
```

```yaml
  my_hop:
    input: data/inputs/hop.npz
    edit: {mode: sideways_please, keyframes: [landing]}
    psi: {raw: 0.2, easy: [[0.05, 0.25]], hard: [[0.25, 0.5]]}
```
"""


def test_made_up_commands_flags_paths_and_keys_are_each_caught(monkeypatch, capsys):
    problems = page_problems(MADE_UP, monkeypatch, capsys)
    expected = ["`adamimic fly", "has no option --colour", "make deploy-to-mars", "feet_position",
                "learning_rate_of_doom", "pipeline/nowhere/thing.py", "#no-such-chapter", "--made-up-flag",
                "--psi far", "learn_cpu.py` has no option --no-such-option", "train_stage1.py` has no option --fast",
                "no_such_module.py` does not exist", "iterations_stage3", "sideways_please"]
    for fragment in expected:
        assert any(fragment in p for p in problems), (fragment, problems)
    assert len(problems) == len(expected), problems


def test_real_commands_flags_paths_and_keys_pass(monkeypatch, capsys):
    real = """
`adamimic share` with `--repo-id`; `adamimic play --help`; `make test`; `env.rewards.sigma2.feet_pos`; `tasks.<name>.push_prior.knots`;
`train.time_limit_stage{1,2}_s`; `results/<task>/<variant>/media/`; `data/retargeted/<task>/quality.json`;
[results](docs/results.md), [where](benchmarks/RESULTS.md#where-it-stands).

```bash
.venv/bin/adamimic sim2sim models/far_jump_sample/adamimic/export --psi 0.4 0.6
adamimic share --help
.venv/bin/python benchmarks/learn_cpu.py --segment 2.3 --set env.observations.psi_scale=samples
.venv/bin/python stages/train_stage1.py --task T --variant V --resume
dvc exp run -S profile=gpu -S 'variants=[adamimic]' -S train.ppo.l2c2_fraction=0.25
```

```yaml
env:
  rewards: {sigma2: {feet_pos: 0.03}}
train: {iterations_stage1: 10}
tasks:
  hop: {extends: high_jump, input: data/inputs/hop.npz}
```
"""
    assert page_problems(real, monkeypatch, capsys) == []


USER_FACING = [*PAGES, ROOT / "benchmarks" / "RESULTS.md", *sorted((ROOT / "models" / "pretrained").glob("*/README.md"))]


@pytest.mark.parametrize("page", USER_FACING, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_figures_are_dated_by_day_or_commit_not_by_work_session(page):
    """A reader cannot look up "session 31"; a date or a commit (`git show`) they can."""
    hits = [line.strip()[:80] for line in page.read_text().splitlines() if re.search(r"\bsessions? \d", line, re.I)]
    assert hits == []
