"""Success over training seeds: `extra_seeds` in params.yaml, and the report's aggregation of the
main run's metrics with each extra seed's (reports/<task>/seeds.json and the table's seeds section)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import yaml

from pipeline import REPO_ROOT
from pipeline.common.errors import PipelineInputError
from pipeline.config import load_params
from pipeline.evaluation.report import seed_summary, write_report

COMMITTED_METRICS = REPO_ROOT / "results/far_jump_sample/adamimic/metrics.json"


def _doc(easy: float, hard: float, overall: float, e_g_bpe: float = 125.9) -> dict:
    doc = json.loads(COMMITTED_METRICS.read_text())
    doc = copy.deepcopy(doc)
    for name, value in (("easy", easy), ("hard", hard), ("overall", overall)):
        doc["ranges"][name]["success"] = {"mean": value, "std": 0.0}
        doc["ranges"][name]["e_g_bpe"] = {"mean": e_g_bpe, "std": 0.0}
    return doc


def _write(results: Path, rel: str, doc: dict) -> None:
    path = results / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))


def test_seed_summary_gives_mean_sample_std_and_range():
    summary = seed_summary({0: _doc(18.75, 0.0, 9.375), 1: _doc(0.0, 0.0, 0.0), 2: _doc(6.25, 3.125, 4.6875)})
    easy = summary["ranges"]["easy"]
    assert summary["seeds"] == [0, 1, 2]
    assert easy["success_per_seed"] == {"0": 18.75, "1": 0.0, "2": 6.25}
    assert easy["success_mean"] == pytest.approx(25.0 / 3)
    assert easy["success_std"] == pytest.approx(9.5470, abs=1e-4)  # sample std (ddof 1) of 18.75, 0, 6.25
    assert (easy["success_min"], easy["success_max"]) == (0.0, 18.75)
    assert summary["ranges"]["hard"]["success_mean"] == pytest.approx(3.125 / 3)
    assert seed_summary({0: _doc(1.0, 2.0, 1.5)})["ranges"]["easy"]["success_std"] is None


def test_report_aggregates_the_main_run_and_the_extra_seeds(tmp_path):
    results, out = tmp_path / "results", tmp_path / "reports"
    _write(results, "adamimic/metrics.json", _doc(18.75, 0.0, 9.375))
    _write(results, "adamimic/seeds/1/metrics.json", _doc(0.0, 0.0, 0.0))
    _write(results, "adamimic/seeds/4/metrics.json", _doc(12.5, 6.25, 9.375, e_g_bpe=140.0))
    table = write_report("far_jump_sample", ["adamimic"], results, out, seeds=(0, 1, 4)).read_text()
    seeds = json.loads((out / "seeds.json").read_text())["adamimic"]
    assert seeds["seeds"] == [0, 1, 4]
    assert seeds["ranges"]["overall"]["success_per_seed"] == {"0": 9.375, "1": 0.0, "4": 9.375}
    assert "## Success over training seeds (3: 0, 1, 4)" in table
    assert "| adamimic | 10.4 ± 9.5 [0.0–18.8] | 2.1 ± 3.6 [0.0–6.2] | 6.2 ± 5.4 [0.0–9.4] |" in table
    assert "seed 0: 18.8 / 0.0 / 9.4, 125.9 mm; seed 1: 0.0 / 0.0 / 0.0, 125.9 mm; seed 4: 12.5 / 6.2 / 9.4, 140.0 mm" in table
    # the body error's spread beside success's: mean [min–max] of the overall E_g-bpe
    assert "| 6.2 ± 5.4 [0.0–9.4] | 130.6 [125.9–140.0] |" in table
    assert seeds["ranges"]["overall"]["e_g_bpe_per_seed"] == {"0": 125.9, "1": 125.9, "4": 140.0}
    # The main run's table is still the first seed's own.
    assert "| adamimic | 18.8 ± 0.0 |" in table


def test_report_names_a_missing_seed_evaluation(tmp_path):
    results = tmp_path / "results"
    _write(results, "adamimic/metrics.json", _doc(18.75, 0.0, 9.375))
    with pytest.raises(PipelineInputError) as error:
        write_report("far_jump_sample", ["adamimic"], results, tmp_path / "reports", seeds=(0, 3))
    assert "seeds/3/metrics.json" in str(error.value) and "evaluate_seed" in str(error.value)
    assert not (tmp_path / "reports" / "seeds.json").exists()


def test_one_seed_report_has_no_seeds_section(tmp_path):
    results = tmp_path / "results"
    _write(results, "adamimic/metrics.json", _doc(18.75, 0.0, 9.375))
    table = write_report("far_jump_sample", ["adamimic"], results, tmp_path / "reports", seeds=(0,)).read_text()
    assert "training seeds" not in table
    assert json.loads((tmp_path / "reports/seeds.json").read_text())["adamimic"]["seeds"] == [0]


def test_a_comparison_seeds_only_its_seed_variants(tmp_path):
    """`seed_variants`: the rows trained again at the extra seeds; the others are the first seed's alone,
    and the report neither asks for their seeds nor lists them over seeds."""
    results, out = tmp_path / "results", tmp_path / "reports"
    _write(results, "adamimic/metrics.json", _doc(96.9, 68.8, 82.8, e_g_bpe=161.0))
    _write(results, "adamimic/seeds/1/metrics.json", _doc(90.6, 62.5, 76.6, e_g_bpe=170.0))
    _write(results, "deepmimic_adapt/metrics.json", _doc(100.0, 81.2, 90.6, e_g_bpe=268.0))
    table = write_report("far_jump_window", ["adamimic", "deepmimic_adapt"], results, out, seeds=(0, 1),
                         seed_variants=["adamimic"]).read_text()
    assert list(json.loads((out / "seeds.json").read_text())) == ["adamimic"]
    seeds_section = table.split("## Success over training seeds (2: 0, 1)")[1]
    assert "| adamimic | 93.8 ± 4.5 [90.6–96.9] |" in seeds_section
    assert "trained at the first seed only: deepmimic_adapt (`seed_variants`)" in seeds_section
    assert "| deepmimic_adapt |" not in seeds_section.split("\n## ")[0]
    with pytest.raises(PipelineInputError) as error:  # a seeded row without its evaluation is still named
        write_report("far_jump_window", ["adamimic", "deepmimic_adapt"], results, out, seeds=(0, 1),
                     seed_variants=["deepmimic_adapt"])
    assert "deepmimic_adapt/seeds/1/metrics.json" in str(error.value)


@pytest.mark.parametrize(
    "value, key",
    [("adamimic", "seed_variants"), (["amp_style"], "seed_variants[0]"), (["adamimic", "adamimic"], "seed_variants")],
)
def test_bad_seed_variants_name_the_key(tmp_path, value, key):
    raw = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    raw["seed_variants"] = value
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(PipelineInputError) as error:
        load_params(path)
    assert key in str(error.value)


def test_seed_variants_default_to_every_variant(tmp_path):
    raw = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    raw.pop("seed_variants", None)
    raw["variants"] = ["adamimic", "adamimic_stage1"]
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert load_params(path).seed_variants == ("adamimic", "adamimic_stage1")


def test_default_params_train_three_seeds():
    params = load_params(REPO_ROOT / "params.yaml")
    assert params.seeds == (params.train.seed, *params.extra_seeds)
    assert len(params.seeds) >= 3 and len(set(params.seeds)) == len(params.seeds)


@pytest.mark.parametrize(
    "value, key",
    [("1, 2", "extra_seeds"), ([1, "two"], "extra_seeds[1]"), ([1, -1], "extra_seeds[1]"),
     ([0, 1], "extra_seeds[0]"), ([1, 1], "extra_seeds"), ([True], "extra_seeds[0]")],
)
def test_bad_extra_seeds_name_the_key(tmp_path, value, key):
    raw = yaml.safe_load((REPO_ROOT / "params.yaml").read_text())
    raw["extra_seeds"] = value
    raw["train"]["seed"] = 0
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(PipelineInputError) as error:
        load_params(path)
    assert key in str(error.value)
