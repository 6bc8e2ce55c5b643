"""docs/results.md generator (pipeline/evaluation/results_page.py) on small made-up result folders."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.evaluation.page_images import GIF_WIDTH, MAX_GIF_BYTES, MAX_IMAGE_BYTES
from pipeline.evaluation.results_page import PAPER_TITLE, main, write_results_page


def _stat(mean, std=0.0):
    return {"mean": mean, "std": std}


def _metrics(task, variant, success_easy, success_hard):
    ranges = {}
    for name, success in (("easy", success_easy), ("hard", success_hard),
                          ("overall", (success_easy + success_hard) / 2)):
        ranges[name] = {"success": _stat(success, 1.25), "e_l_bpe": _stat(33.3), "e_g_bpe": _stat(123.4),
                        "e_smth": _stat(7.5), "psi_reached": _stat(0.5), "psi_reached_max": _stat(math.nan),
                        "episodes": {"total": 64, "runs": 2}}
    return {"task": task, "variant": variant, "psi_ranges": {"easy": [[0.5, 1.0]], "hard": [[1.0, 1.5]]},
            "ranges": ranges, "psi_raw": 0.77, "policy_stage": 2,
            "endings": {"episodes": 64, "ending": {"completed": 25.0, "forward": 75.0},
                        "check": {"tilt": 75.0}}}


def _write_result(folder: Path, doc: dict, per_psi: list[tuple[float, float]] | None) -> None:
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps(doc))
    if per_psi is not None:
        lines = ["psi,psi_lo,psi_hi,success,e_l_bpe,e_g_bpe,e_smth,psi_reached,psi_reached_max,episodes"]
        lines += [f"{psi},{psi - 0.05},{psi + 0.05},{success},30,120,7,0.5,nan,8" for psi, success in per_psi]
        (folder / "per_psi.csv").write_text("\n".join(lines) + "\n")


def _png(path: Path, width=1600, height=900) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)  # noise: a large PNG, so the page has to shrink it
    Image.fromarray(rng.integers(0, 255, (height, width, 3), dtype=np.uint8)).save(path)


def _video(path: Path, frames=30) -> None:
    from pipeline.render.mp4 import Mp4Writer

    path.parent.mkdir(parents=True, exist_ok=True)
    writer = Mp4Writer(path, fps=25, width=160, height=96)
    for k in range(frames):
        frame = np.zeros((96, 160, 3), dtype=np.uint8)
        frame[:, (k * 5) % 160:(k * 5) % 160 + 10] = 255  # a moving bar
        writer.add(frame)
    writer.close()


@pytest.fixture
def made_up_repo(tmp_path):
    root = tmp_path
    _write_result(root / "results" / "hop" / "adamimic", _metrics("hop", "adamimic", 62.5, 12.5),
                  [(0.55, 100.0), (0.8, 50.0), (1.2, 12.5), (1.45, 0.0)])
    _write_result(root / "results" / "hop" / "deepmimic_adapt", _metrics("hop", "deepmimic_adapt", 31.25, 0.0),
                  [(0.55, 50.0), (0.8, 12.5), (1.2, 0.0)])
    _png(root / "data" / "keyframes" / "hop" / "keyframes.png")
    _video(root / "results" / "hop" / "adamimic" / "media" / "easy_psi0.75.mp4")
    _write_result(root / "models" / "pretrained" / "leap", _metrics("leap", "adamimic", 87.5, 50.0), None)
    _png(root / "models" / "pretrained" / "leap" / "keyframes.png")  # its own figure: no data/keyframes/leap
    (root / "models" / "pretrained" / "recipe_only").mkdir(parents=True)
    (root / "models" / "pretrained" / "recipe_only" / "README.md").write_text("# a recipe\n")
    return root


def test_page_holds_each_task_table_plot_keyframes_and_rollout(made_up_repo):
    root = made_up_repo
    page = write_results_page(root)
    text = page.read_text()
    assert page == root / "docs" / "results.md"

    # the table in the paper's layout, both variants of the task, figures as the metrics hold them
    assert "## hop" in text
    assert "| Method | easy Succ.↑ | easy E_l-bpe↓ | easy E_g-bpe↓ | easy E_smth↓ | hard Succ.↑" in text
    assert "| adamimic | 62.5 ± 1.2 | 33.3 ± 0.0 | 123.4 ± 0.0 | 7.50 ± 0.00 | 12.5 ± 1.2 |" in text
    assert "| deepmimic_adapt | 31.2 ± 1.2 |" in text
    assert "easy [0.5, 1]; hard [1, 1.5]" in text and "the clip's own ψ 0.77" in text
    assert "64 episodes over 2 runs" in text
    assert "25 % ran to the end; 75 % fell forward" in text
    # no paper figure is made up on the page: it names the paper and points to the report, which prints the
    # paper's rows from the figures file
    assert "the report stage prints the paper's own rows beside ours" in text and PAPER_TITLE in text
    assert "99.6" not in text  # the paper's AdaMimic easy success

    images = root / "docs" / "img" / "results" / "hop"
    for name in ("success_vs_psi.png", "keyframes.png", "rollout_adamimic.gif"):
        assert (images / name).is_file(), name
        assert (images / name).stat().st_size < (MAX_GIF_BYTES if name.endswith(".gif") else MAX_IMAGE_BYTES), name
        assert f"](img/results/hop/{name})" in text
    # the keyframe figure came from a 1600 px, ~4 MB noise PNG: shrunk to fit
    from PIL import Image

    assert Image.open(images / "keyframes.png").width <= 900
    gif = Image.open(images / "rollout_adamimic.gif")
    assert gif.n_frames > 1 and gif.width == GIF_WIDTH == 640
    # the variant without a video says so instead of showing someone else's
    assert "deepmimic_adapt: no rollout video in `results/hop/deepmimic_adapt/media/`" in text
    assert not (images / "rollout_deepmimic_adapt.gif").exists()

    # the committed policy gets its own section without a plot (no per_psi.csv); the recipe is listed
    assert "## leap" in text and "| adamimic | 87.5 ± 1.2 |" in text
    assert "No `per_psi.csv` beside the metrics" in text
    assert "Keyframes and their edits (`models/pretrained/leap/keyframes.png`)" in text
    assert (root / "docs" / "img" / "results" / "leap" / "keyframes.png").is_file()
    assert "[`models/pretrained/recipe_only/README.md`](../models/pretrained/recipe_only/README.md)" in text
    assert "`leap`:" not in text  # a folder with metrics is not a recipe


def test_the_page_is_the_same_when_rerun_and_keeps_images_whose_sources_are_gone(made_up_repo):
    root = made_up_repo
    first = write_results_page(root).read_text()
    images = root / "docs" / "img" / "results" / "hop"
    kept = {p.name: p.read_bytes() for p in images.iterdir()}
    # a fresh clone: the DVC outputs (keyframe figure, videos) are not there
    (root / "data" / "keyframes" / "hop" / "keyframes.png").unlink()
    (root / "results" / "hop" / "adamimic" / "media" / "easy_psi0.75.mp4").unlink()
    second = write_results_page(root).read_text()
    assert {p.name: p.read_bytes() for p in images.iterdir()} == kept
    assert "](img/results/hop/keyframes.png)" in second and "](img/results/hop/rollout_adamimic.gif)" in second
    assert second.replace("a rollout video of `results/hop/adamimic/media/`",
                          "`results/hop/adamimic/media/easy_psi0.75.mp4`") == first


def test_a_new_result_changes_the_page(made_up_repo):
    root = made_up_repo
    before = write_results_page(root).read_text()
    doc = _metrics("hop", "adamimic", 100.0, 75.0)
    (root / "results" / "hop" / "adamimic" / "metrics.json").write_text(json.dumps(doc))
    after = write_results_page(root).read_text()
    assert "| adamimic | 100.0 ± 1.2 |" in after and "| adamimic | 100.0 ± 1.2 |" not in before


def test_the_spread_over_training_seeds_comes_from_the_report(made_up_repo):
    from pipeline.evaluation.report import seed_summary

    root = made_up_repo
    assert "Success over training seeds" not in write_results_page(root).read_text()
    by_seed = {0: _metrics("hop", "adamimic", 62.5, 12.5), 1: _metrics("hop", "adamimic", 12.5, 0.0),
               2: _metrics("hop", "adamimic", 37.5, 25.0)}
    seeds = root / "reports" / "hop" / "seeds.json"
    seeds.parent.mkdir(parents=True)
    seeds.write_text(json.dumps({"adamimic": seed_summary(by_seed)}))
    page = write_results_page(root).read_text()
    hop = page[page.index("## hop"):page.index("## leap")]
    assert "### Success over training seeds (3: 0, 1, 2)" in hop
    assert "| adamimic | 37.5 ± 25.0 [12.5–62.5] |" in hop  # easy: mean ± sample std [min–max]
    assert "(../reports/hop/seeds.json)" in hop

    seeds.write_text(json.dumps({"adamimic": {"seeds": [0, 1]}}))
    with pytest.raises(PipelineInputError) as error:
        write_results_page(root)
    assert error.value.source == str(seeds) and error.value.field == "adamimic"
    truncated = seed_summary(by_seed)
    del truncated["ranges"]["hard"]["success_per_seed"]["2"]
    seeds.write_text(json.dumps({"adamimic": truncated}))
    for image in [p for p in (root / "docs" / "img" / "results").rglob("*") if p.is_file()]:
        image.unlink()
    with pytest.raises(PipelineInputError) as error:
        write_results_page(root)
    assert error.value.field == "adamimic.ranges.hard.success_per_seed"
    assert not any(p.is_file() for p in (root / "docs" / "img" / "results").rglob("*"))  # read before writing
    assert (root / "docs" / "results.md").read_text() == page  # the last good page stays


@pytest.mark.parametrize("breakage, field", [
    (lambda doc: doc.pop("ranges"), "ranges"),
    (lambda doc: doc["ranges"]["easy"].pop("e_g_bpe"), "ranges.easy.e_g_bpe"),
    (lambda doc: doc.pop("psi_ranges"), "psi_ranges"),
])
def test_bad_metrics_name_the_file_and_field_and_write_nothing(made_up_repo, breakage, field):
    root = made_up_repo
    path = root / "results" / "hop" / "deepmimic_adapt" / "metrics.json"
    doc = json.loads(path.read_text())
    breakage(doc)
    path.write_text(json.dumps(doc))
    with pytest.raises(PipelineInputError) as error:
        write_results_page(root)
    assert error.value.source == str(path) and error.value.field == field
    assert not (root / "docs").exists()


def test_a_per_psi_csv_without_success_is_refused(made_up_repo):
    root = made_up_repo
    path = root / "results" / "hop" / "adamimic" / "per_psi.csv"
    path.write_text("psi,e_g_bpe\n0.5,100\n")
    with pytest.raises(PipelineInputError, match="success: missing column"):
        write_results_page(root)


def test_cli_writes_the_page_and_exits_2_on_bad_input(made_up_repo, capsys):
    root = made_up_repo
    main(["--root", str(root)])
    assert (root / "docs" / "results.md").is_file()
    (root / "results" / "hop" / "adamimic" / "metrics.json").write_text("{not json")
    with pytest.raises(SystemExit) as exit_info:
        main(["--root", str(root), "--out", "elsewhere.md"])
    assert exit_info.value.code == 2
    assert "metrics.json: not valid JSON" in capsys.readouterr().err
    assert not (root / "elsewhere.md").exists()
