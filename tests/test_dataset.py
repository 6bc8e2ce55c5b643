"""The LeRobot v3.0 writer/reader: layout, exact round trip, bad input, and lerobot's own reader."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.common.errors import PipelineInputError
from pipeline.dataset.lerobot import Feature, read_dataset, write_dataset

REPO = Path(__file__).resolve().parents[1]
FEATURES = {
    "state": Feature("float64", (3,), ["a", "b", "c"]),
    "pose": Feature("float64", (2, 4), ["left", "right"]),
    "psi": Feature("float32", (1,)),
    "count": Feature("int64", (1,)),
}


def _episodes():
    rng = np.random.default_rng(7)
    out = []
    for length, psi in ((5, 0.25), (8, 0.75), (3, 0.5)):
        out.append({
            "state": rng.normal(size=(length, 3)),
            "pose": rng.normal(size=(length, 2, 4)),
            "psi": np.full((length, 1), psi, np.float32),  # per-episode scalar: a constant column
            "count": np.arange(length, dtype=np.int64)[:, None] * 10,
        })
    return out


TASKS = ["jump gap", "climb step", "jump gap"]


@pytest.fixture
def written(tmp_path):
    root = tmp_path / "ds"
    write_dataset(root, fps=50, features=FEATURES, episodes=_episodes(), tasks=TASKS, extra={"psi": [0.25, 0.75, 0.5]})
    return root


def test_layout_matches_lerobot_v3(written):
    for rel in ("meta/info.json", "meta/stats.json", "meta/tasks.parquet",
                "meta/episodes/chunk-000/file-000.parquet", "data/chunk-000/file-000.parquet"):
        assert (written / rel).is_file(), rel
    info = json.loads((written / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0"
    assert info["fps"] == 50 and info["total_episodes"] == 3 and info["total_frames"] == 16
    assert info["total_tasks"] == 2 and info["robot_type"] == "unitree_g1"
    assert info["features"]["pose"] == {"dtype": "float64", "shape": [2, 4], "names": ["left", "right"]}
    for column in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert column in info["features"]
    data = pq.read_table(written / "data/chunk-000/file-000.parquet")
    assert data.column("index").to_pylist() == list(range(16))
    assert data.column("frame_index").to_pylist()[5:8] == [0, 1, 2]
    assert data.column("task_index").to_pylist()[-3:] == [0, 0, 0]  # task strings shared by index
    episodes = pq.read_table(written / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [e["dataset_from_index"] for e in episodes] == [0, 5, 13]
    assert [e["tasks"] for e in episodes] == [[t] for t in TASKS]
    stats = json.loads((written / "meta/stats.json").read_text())
    assert stats["state"]["count"] == [16]
    assert len(stats["pose"]["mean"]) == 4  # reduced over frames and all axes but the last


def test_round_trip_exact(written):
    data = read_dataset(written)
    assert data.fps == 50.0 and data.tasks == TASKS
    assert data.features == FEATURES
    assert data.extra == {"psi": [0.25, 0.75, 0.5]}
    for got, want in zip(data.episodes, _episodes()):
        assert set(got) == set(FEATURES)
        for key in FEATURES:
            assert got[key].dtype == np.dtype(FEATURES[key].dtype)
            np.testing.assert_array_equal(got[key], want[key])


def _rewrite_info(root, **changes):
    path = root / "meta/info.json"
    info = json.loads(path.read_text())
    info.update(changes)
    path.write_text(json.dumps(info))


@pytest.mark.parametrize(
    "damage, where, field",
    [
        (lambda r: (r / "meta/info.json").unlink(), "info.json", None),
        (lambda r: (r / "meta/info.json").write_text("{not json"), "info.json", None),
        (lambda r: _rewrite_info(r, fps=-5), "info.json", "fps"),
        (lambda r: _rewrite_info(r, codebase_version="v2.1"), "info.json", "codebase_version"),
        (lambda r: (r / "meta/tasks.parquet").unlink(), "tasks.parquet", None),
        (lambda r: (r / "data/chunk-000/file-000.parquet").write_bytes(b"garbage"), "file-000.parquet", None),
        (lambda r: pq.write_table(pq.read_table(r / "data/chunk-000/file-000.parquet").drop_columns(["pose"]),
                                  r / "data/chunk-000/file-000.parquet"), "data", "pose"),
    ],
)
def test_read_errors_name_file_and_field(written, damage, where, field):
    damage(written)
    with pytest.raises(PipelineInputError) as err:
        read_dataset(written)
    assert where in err.value.source
    assert err.value.field == field


def test_read_rejects_nan(written):
    import pyarrow as pa

    path = written / "data/chunk-000/file-000.parquet"
    table = pq.read_table(path)
    state = np.array(table.column("state").to_pylist())
    state[4, 1] = np.nan
    col = pa.FixedSizeListArray.from_arrays(pa.array(state.reshape(-1)), 3)
    pq.write_table(table.set_column(table.column_names.index("state"), "state", col), path)
    with pytest.raises(PipelineInputError, match="NaN") as err:
        read_dataset(written)
    assert err.value.field == "state"


def test_missing_dataset(tmp_path):
    with pytest.raises(PipelineInputError, match="missing"):
        read_dataset(tmp_path / "nope")


def _bad_episode(key, value):
    episodes = _episodes()
    episodes[1][key] = value
    return episodes


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"fps": 0}, "fps"),
        ({"fps": float("nan")}, "fps"),
        ({"episodes": _bad_episode("state", np.full((8, 3), np.inf))}, "episodes[1].state"),
        ({"episodes": _bad_episode("pose", np.zeros((8, 4, 2)))}, "episodes[1].pose"),
        ({"episodes": _bad_episode("psi", np.zeros((7, 1), np.float32))}, "episodes[1].psi"),
        ({"tasks": TASKS[:2]}, "tasks"),
        ({"features": {**FEATURES, "a/b": Feature("float64", (1,))}}, "features.a/b"),
        ({"features": {**FEATURES, "index": Feature("int64", (1,))}}, "features.index"),
        ({"extra": {"bad": object()}}, "extra"),
    ],
)
def test_write_refuses_bad_input_and_leaves_target_unchanged(tmp_path, kwargs, field):
    root = tmp_path / "ds"
    write_dataset(root, fps=30, features={"x": Feature("float64", (1,))}, episodes=[{"x": np.ones((2, 1))}], tasks=["old"])
    before = {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}
    args = {"fps": 50, "features": FEATURES, "episodes": _episodes(), "tasks": TASKS, **kwargs}
    with pytest.raises(PipelineInputError) as err:
        write_dataset(root, **args)
    assert err.value.field == field and str(root) in err.value.source
    after = {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]  # no staging left over


def test_failure_during_write_leaves_no_target(tmp_path, monkeypatch):
    import pipeline.dataset.lerobot as module

    def explode(*_args, **_kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(module, "_write_table", explode)
    with pytest.raises(OSError):
        write_dataset(tmp_path / "ds", fps=50, features=FEATURES, episodes=_episodes(), tasks=TASKS)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------- lerobot's own reader
# lerobot 0.4.4 is installed by `make setup` with --no-deps (its releases pin torch<2.12) plus the
# light modules `lerobot.datasets` imports. `lerobot.datasets.utils` and `video_utils` import
# torchvision at module level, but use it only to decode videos and convert images; PyPI's
# torchvision for torch 2.13 is a CUDA build whose compiled ops cannot load next to CPU torch
# (`import torchvision` fails: "operator torchvision::nms does not exist"). The child process
# therefore gets a stand-in `torchvision` module that raises if anything of it is used: a dataset
# without images or videos never touches it, so the check below exercises lerobot's real code.
TORCHVISION_STAND_IN = '''
"""Stand-in for tests: lerobot imports torchvision at module level for images/videos only."""
import sys, types

def _unavailable(name):
    raise RuntimeError(f"torchvision stand-in: {name} used (only image/video paths need it)")

transforms = types.ModuleType("torchvision.transforms")
transforms.__getattr__ = lambda name: _unavailable(f"transforms.{name}")
sys.modules["torchvision.transforms"] = transforms

def __getattr__(name):
    _unavailable(name)
'''

LEROBOT_CHECK = textwrap.dedent('''
    import json, sys
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    root, out = sys.argv[1], sys.argv[2]
    ds = LeRobotDataset("local/adamimic_test", root=root)
    frames = []
    for i in range(len(ds)):
        item = ds[i]
        frames.append({k: (v.numpy().tolist() if hasattr(v, "numpy") else v) for k, v in item.items()})
    raw = ds.hf_dataset.with_format(None)  # the stored values, before lerobot's float32 tensors
    json.dump({
        "len": len(ds), "num_episodes": ds.num_episodes, "fps": ds.fps,
        "features": {k: v["shape"] for k, v in ds.meta.features.items()},
        "names": ds.meta.names, "tasks": list(ds.meta.tasks.index),
        "episodes": [dict(from_=e["dataset_from_index"], to=e["dataset_to_index"]) for e in ds.meta.episodes],
        "frames": frames,
        "raw_pose": [raw[i]["pose"] for i in range(len(ds))],
        "raw_state": [raw[i]["state"] for i in range(len(ds))],
        "stats_keys": sorted(ds.meta.stats),
    }, open(out, "w"))
''')


def test_lerobot_reader_loads_our_dataset(written, tmp_path):
    try:
        import importlib.util

        found = importlib.util.find_spec("lerobot") is not None
    except ValueError:
        found = False
    assert found, "lerobot is missing: run `make setup` (installs lerobot==0.4.4 with --no-deps)"
    stand_in = tmp_path / "stand_in"
    (stand_in / "torchvision").mkdir(parents=True)
    (stand_in / "torchvision/__init__.py").write_text(TORCHVISION_STAND_IN)
    env = {
        **os.environ,
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "HF_HOME": str(tmp_path / "hf_home"),  # no cache from elsewhere, nothing left behind
        "PYTHONPATH": os.pathsep.join([str(stand_in), str(REPO)]),
    }
    out = tmp_path / "lerobot.json"
    proc = subprocess.run([sys.executable, "-c", LEROBOT_CHECK, str(written), str(out)],
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(out.read_text())
    episodes = _episodes()
    assert got["len"] == 16 and got["num_episodes"] == 3 and got["fps"] == 50
    assert got["features"]["pose"] == [2, 4] and got["names"]["state"] == ["a", "b", "c"]
    assert got["tasks"] == ["jump gap", "climb step"]
    assert got["episodes"] == [{"from_": 0, "to": 5}, {"from_": 5, "to": 13}, {"from_": 13, "to": 16}]
    assert "pose" in got["stats_keys"]
    flat = [(e, t) for e, ep in enumerate(episodes) for t in range(len(ep["state"]))]
    for i, (e, t) in enumerate(flat):
        frame = got["frames"][i]
        assert frame["episode_index"] == e and frame["frame_index"] == t and frame["index"] == i
        assert frame["task"] == TASKS[e]
        assert frame["timestamp"] == pytest.approx(t / 50, abs=1e-6)
        # lerobot hands out float32 tensors; the stored float64 values come back exactly.
        np.testing.assert_array_equal(np.float32(frame["pose"]), episodes[e]["pose"][t].astype(np.float32))
        np.testing.assert_array_equal(np.array(got["raw_pose"][i]), episodes[e]["pose"][t])
        np.testing.assert_array_equal(np.array(got["raw_state"][i]), episodes[e]["state"][t])
        assert frame["psi"] == pytest.approx(float(episodes[e]["psi"][t, 0]))
        assert frame["count"] == episodes[e]["count"][t, 0]
