"""The paper's rows beside ours and its claims, on made-up result folders and a made-up figures file."""

import json

import yaml

from pipeline.evaluation.paper import load_paper_rows, paper_section
from pipeline.evaluation.report import write_report

PAPER = {"main_simulation": {"columns": ["success", "e_l_bpe", "e_g_bpe", "e_smth"], "rows": {
    "adamimic": {"easy": [99.6, 30.3, 87.9, 16.0], "hard": [74.2, 30.3, 99.8, 17.3], "overall": [86.8, 30.3, 94.8, 16.6]},
    "adamimic_stage1": {"easy": [96.7, 43.4, 188.1, 17.8], "hard": [75.2, 43.4, 211.8, 18.7],
                        "overall": [85.7, 43.4, 200.4, 18.2]},
    "deepmimic_adapt": {"easy": [95.8, 33.3, 123.6, 15.1], "hard": [74.8, 33.3, 142.8, 16.7],
                        "overall": [85.1, 33.3, 133.5, 15.9]}}}}


def _metrics(success, e_g_bpe):
    stat = lambda m: {"mean": m, "std": 0.0}  # noqa: E731
    ranges = {g: {"success": stat(success), "e_l_bpe": stat(40.0), "e_g_bpe": stat(e_g_bpe), "e_smth": stat(20.0),
                  "episodes": {"total": 10, "runs": 1}} for g in ("easy", "hard", "overall")}
    return {"task": "far_jump", "variant": "x", "psi_ranges": {"easy": [[0.7, 1.6]]}, "ranges": ranges}


def _results(tmp_path, rows):
    for variant, (success, e_g_bpe) in rows.items():
        folder = tmp_path / "results" / variant
        folder.mkdir(parents=True)
        (folder / "metrics.json").write_text(json.dumps(_metrics(success, e_g_bpe)))
    return tmp_path / "results"


def test_our_rows_beside_the_papers_and_the_claims_checked(tmp_path):
    figures = tmp_path / "figures.yaml"
    figures.write_text(yaml.safe_dump(PAPER))
    results = _results(tmp_path, {"adamimic": (90.0, 150.0), "adamimic_stage1": (95.0, 120.0),
                                  "deepmimic_adapt": (80.0, 200.0)})
    table = write_report("far_jump", ["adamimic", "adamimic_stage1", "deepmimic_adapt"], results, tmp_path / "out",
                         figures=figures).read_text()
    assert "| adamimic | 90.0 |" in table and "| adamimic (paper) | 99.6 | 30.3 | 87.9 | 16.0 | 74.2 |" in table
    assert "Isaac Gym, 4096 envs" in table
    # ours: the adapters did not lower E_g-bpe (150 > 120), keyframe edits did beat dense tracking (150 < 200)
    assert "adamimic < adamimic_stage1): here does not hold; in the paper's rows holds" in table
    assert "adamimic < deepmimic_adapt): here holds; in the paper's rows holds" in table
    assert "freezing stage 1 beats not freezing it" in table and "not measured (a variant is missing)" in table
    assert "at least every baseline's (deepmimic_adapt): here holds" in table


def test_without_the_figures_file_the_report_says_so(tmp_path):
    results = _results(tmp_path, {"adamimic": (90.0, 150.0)})
    table = write_report("far_jump", ["adamimic"], results, tmp_path / "out", figures=tmp_path / "nowhere.yaml").read_text()
    assert "The paper's figures file is not at" in table and "(paper)" not in table
    assert load_paper_rows(tmp_path / "nowhere.yaml") is None


def test_a_malformed_figures_file_names_the_key(tmp_path):
    import pytest

    from pipeline.common.errors import PipelineInputError

    bad = tmp_path / "figures.yaml"
    bad.write_text(yaml.safe_dump({"main_simulation": {"columns": ["success"], "rows": {}}}))
    with pytest.raises(PipelineInputError, match="main_simulation.columns"):
        paper_section({}, bad)


def test_the_chain_table_keeps_its_rows_together_and_the_endings_below(tmp_path):
    """Two chained variants: a line between their rows would end the markdown table after the first."""
    from pipeline.evaluation.report import rest_to_rest_table

    docs = {}
    for variant in ("adamimic", "adamimic_stage1"):
        doc = _metrics(90.0, 150.0)
        for r in doc["ranges"].values():
            r["rest_to_rest"] = {"mean": 0.0}
        doc["chain"] = {"endings": {"task:tilt": 64}}
        docs[variant] = doc
    lines = rest_to_rest_table(docs, {}).splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("| adamimic |"))
    assert lines[first + 1].startswith("| adamimic_stage1 |")
    assert [line for line in lines[first + 2:] if "where the chains ended" in line] == [
        "adamimic, where the chains ended (stretch:check, episodes): task:tilt 64",
        "adamimic_stage1, where the chains ended (stretch:check, episodes): task:tilt 64"]


def test_the_committed_comparison_table_is_the_report_over_its_committed_rows(tmp_path):
    """`models/pretrained/far_jump/comparison/table.md` is what the report stage writes from the rows committed
    beside it (`adamimic`'s: the committed far jump's own evaluation, and its seed 1), every variant of the paper's
    table, with the spread over the training seeds of the rows trained again."""
    import shutil
    from pathlib import Path

    from pipeline.config import load_params
    from pipeline.rl.config import VARIANTS

    folder = Path(__file__).resolve().parent.parent / "models/pretrained/far_jump/comparison"
    params = load_params(folder / "params.yaml")
    assert sorted(params.variants) == sorted(VARIANTS)
    results = tmp_path / "results"
    for variant in params.variants:
        (results / variant).mkdir(parents=True)
        for name in ("metrics.json", "metrics_dr.json", "per_psi.json", "per_psi.csv"):
            shutil.copy((folder.parent if variant == "adamimic" else folder / variant) / name, results / variant / name)
    for variant in params.seed_variants:  # the rows trained again at the extra seeds
        for seed in params.extra_seeds:
            shutil.copytree((folder.parent if variant == "adamimic" else folder / variant) / "seeds" / str(seed),
                            results / variant / "seeds" / str(seed))
    table = write_report("far_jump_window", list(params.variants), results_dir=results, out_dir=tmp_path / "report",
                         seeds=params.seeds, seed_variants=list(params.seed_variants))
    assert Path(table).read_text() == (folder / "table.md").read_text()
