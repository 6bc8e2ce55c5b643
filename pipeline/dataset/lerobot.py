"""A generic writer and reader of the LeRobot v3.0 on-disk dataset layout, with pyarrow only.

Layout (what LeRobot 0.4.x's `LeRobotDataset(repo_id, root=...)` loads offline)::

    <root>/
      meta/info.json                            codebase_version "v3.0", fps, robot_type, totals,
                                                chunks_size, data_path, video_path (null), splits,
                                                features {name: {dtype, shape, names}}
      meta/stats.json                           {feature: {min, max, mean, std, count, q01..q99}}
      meta/tasks.parquet                        one row per distinct task: task_index (int64) and
                                                the task string as the pandas index
                                                (`__index_level_0__` + pandas schema metadata)
      meta/episodes/chunk-000/file-000.parquet  one row per episode: episode_index, tasks (list of
                                                str), length, data/chunk_index, data/file_index,
                                                dataset_from_index, dataset_to_index,
                                                stats/<feature>/<stat>, meta/episodes/chunk_index,
                                                meta/episodes/file_index
      data/chunk-000/file-000.parquet           one row per frame: every declared feature plus
                                                timestamp (float32), frame_index, episode_index,
                                                index (global frame), task_index (all int64)
      meta/pipeline.json                        ours: the caller's `extra` JSON (LeRobot ignores it)

Frame columns by feature shape, as LeRobot's `datasets` schema declares them (kept in the
`huggingface` schema metadata): (1,) -> a scalar column, (n,) -> fixed-size list, 2-D or 3-D ->
nested lists (`Array2D`/`Array3D`). Stats reduce over frames and every axis but the last, so a
(B, 3) feature has (3,) stats, as LeRobot computes them.

Everything is written into a staging directory and swapped in whole (`atomic_dir`); every check
runs before anything is written. Reading checks the files, JSON, columns, shapes and finiteness
and raises `PipelineInputError` naming the file and the field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.common.atomic import atomic_dir
from pipeline.common.errors import PipelineInputError
from pipeline.dataset.columns import (SUPPORTED_DTYPES, Feature, column_values, feature_stats, frame_column,
                                      hf_feature, stats_json)

CODEBASE_VERSION = "v3.0"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EXTRA_PATH = "meta/pipeline.json"
EPISODES_DIR = "meta/episodes"
DATA_DIR = "data"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DATA_PATH_TEMPLATE = f"{DATA_DIR}/{CHUNK_FILE}"
EPISODES_PATH_TEMPLATE = f"{EPISODES_DIR}/{CHUNK_FILE}"
CHUNKS_SIZE = 1000
DATA_FILE_SIZE_MB = 100
VIDEO_FILE_SIZE_MB = 200

# Columns LeRobot adds to every frame, in its order.
INDEX_COLUMNS: dict[str, str] = {
    "timestamp": "float32",
    "frame_index": "int64",
    "episode_index": "int64",
    "index": "int64",
    "task_index": "int64",
}
_TASK_INDEX_COLUMN = "__index_level_0__"


@dataclass
class LeRobotData:
    fps: float
    features: dict[str, Feature]  # the caller's features (index columns left out)
    episodes: list[dict[str, np.ndarray]]  # each value (T_e, *feature.shape)
    tasks: list[str]  # one task string per episode
    extra: dict | None = None
    info: dict = field(default_factory=dict)


# =============================================================================== writing
def _check_features(root: Path, features: dict[str, Feature]) -> None:
    if not features:
        raise PipelineInputError(root, "features", "no features declared")
    for name, feature in features.items():
        where = f"features.{name}"
        if not isinstance(name, str) or not name or "/" in name:
            raise PipelineInputError(root, where, "feature names must be non-empty and contain no '/'")
        if name in INDEX_COLUMNS:
            raise PipelineInputError(root, where, "is a column LeRobot adds itself")
        if feature.dtype not in SUPPORTED_DTYPES:
            raise PipelineInputError(root, where, f"dtype {feature.dtype!r} not in {sorted(SUPPORTED_DTYPES)}")
        shape = tuple(feature.shape)
        if not 1 <= len(shape) <= 3 or any(not isinstance(s, (int, np.integer)) or s < 1 for s in shape):
            raise PipelineInputError(root, where, f"shape must be 1 to 3 positive ints, got {feature.shape}")


def _check_episode(root: Path, e: int, episode: dict, features: dict[str, Feature]) -> int:
    missing = sorted(set(features) - set(episode))
    unknown = sorted(set(episode) - set(features))
    if missing or unknown:
        raise PipelineInputError(root, f"episodes[{e}]", f"missing features {missing}, undeclared {unknown}")
    length = None
    for name, feature in features.items():
        where = f"episodes[{e}].{name}"
        arr = np.asarray(episode[name])
        if arr.ndim != 1 + len(feature.shape) or tuple(arr.shape[1:]) != tuple(feature.shape):
            raise PipelineInputError(root, where, f"expected shape (T, {', '.join(map(str, feature.shape))}), got {arr.shape}")
        if length is None:
            length = arr.shape[0]
        elif arr.shape[0] != length:
            raise PipelineInputError(root, where, f"has {arr.shape[0]} frames, other features {length}")
        if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
            raise PipelineInputError(root, where, "contains NaN/inf")
    if not length:
        raise PipelineInputError(root, f"episodes[{e}]", "has no frames")
    return int(length)



def _write_table(table: pa.Table, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy")


def _json_fps(fps: float) -> int | float:
    # LeRobot stores an int; keep a fractional rate (29.97) exact rather than round it.
    return int(fps) if float(fps).is_integer() else float(fps)


def write_dataset(
    root,
    *,
    fps: float,
    features: dict[str, Feature],
    episodes: list[dict[str, np.ndarray]],
    tasks: list[str],
    robot_type: str = "unitree_g1",
    extra: dict | None = None,
) -> None:
    """Writes `episodes` (each {feature: (T_e, *shape)}) as one LeRobot v3.0 dataset, atomically."""
    root = Path(root)
    features = {name: Feature(f.dtype, tuple(int(s) for s in f.shape), f.names) for name, f in features.items()}
    if not isinstance(fps, (int, float, np.integer, np.floating)) or not math.isfinite(fps) or fps <= 0:
        raise PipelineInputError(root, "fps", f"must be a positive number, got {fps!r}")
    _check_features(root, features)
    if not episodes:
        raise PipelineInputError(root, "episodes", "no episodes to write")
    if len(tasks) != len(episodes):
        raise PipelineInputError(root, "tasks", f"{len(tasks)} task strings for {len(episodes)} episodes")
    for e, task in enumerate(tasks):
        if not isinstance(task, str) or not task:
            raise PipelineInputError(root, f"tasks[{e}]", "must be a non-empty string")
    lengths = [_check_episode(root, e, ep, features) for e, ep in enumerate(episodes)]
    try:
        extra_text = json.dumps(extra, indent=2, allow_nan=False) if extra is not None else None
    except (TypeError, ValueError) as err:
        raise PipelineInputError(root, "extra", f"not JSON-serialisable: {err}") from None

    unique_tasks = list(dict.fromkeys(tasks))
    task_index = [unique_tasks.index(t) for t in tasks]
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    total = int(starts[-1])

    # ---- frames
    columns: dict[str, pa.Array] = {}
    for name, feature in features.items():
        values = np.concatenate([np.asarray(ep[name]) for ep in episodes], axis=0)
        columns[name] = frame_column(values, feature)
    frame_index = np.concatenate([np.arange(n, dtype=np.int64) for n in lengths])
    episode_index = np.repeat(np.arange(len(episodes), dtype=np.int64), lengths)
    index_values = {
        "timestamp": (frame_index / float(fps)).astype(np.float32),
        "frame_index": frame_index,
        "episode_index": episode_index,
        "index": np.arange(total, dtype=np.int64),
        "task_index": np.repeat(np.asarray(task_index, dtype=np.int64), lengths),
    }
    for name, values in index_values.items():
        columns[name] = pa.array(values)
    all_features = {**features, **{n: Feature(d, (1,), None) for n, d in INDEX_COLUMNS.items()}}
    hf_meta = {"info": {"features": {n: hf_feature(f) for n, f in all_features.items()}}}
    data_table = pa.table(columns).replace_schema_metadata({"huggingface": json.dumps(hf_meta)})

    # ---- stats: per episode (into the episodes table) and over the whole dataset
    frame_values = {**{n: np.concatenate([np.asarray(ep[n]) for ep in episodes]) for n in features},
                    **index_values}
    dataset_stats = {name: feature_stats(values) for name, values in frame_values.items()}
    episode_rows: dict[str, list] = {
        "episode_index": list(range(len(episodes))),
        "tasks": [[t] for t in tasks],
        "length": lengths,
        "data/chunk_index": [0] * len(episodes),
        "data/file_index": [0] * len(episodes),
        "dataset_from_index": starts[:-1].tolist(),
        "dataset_to_index": starts[1:].tolist(),
    }
    for e in range(len(episodes)):
        lo, hi = starts[e], starts[e + 1]
        for name, values in frame_values.items():
            for stat, value in feature_stats(values[lo:hi]).items():
                episode_rows.setdefault(f"stats/{name}/{stat}", []).append(np.asarray(value).reshape(-1).tolist())
    episode_rows["meta/episodes/chunk_index"] = [0] * len(episodes)
    episode_rows["meta/episodes/file_index"] = [0] * len(episodes)
    episodes_table = pa.table({
        key: pa.array(rows, type=pa.list_(pa.string())) if key == "tasks" else pa.array(rows)
        for key, rows in episode_rows.items()
    })

    # ---- tasks: pandas reads the task strings back as the frame's index, which LeRobot uses.
    pandas_meta = {
        "index_columns": [_TASK_INDEX_COLUMN],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode",
                            "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
             "numpy_type": "int64", "metadata": None},
            {"name": None, "field_name": _TASK_INDEX_COLUMN, "pandas_type": "unicode",
             "numpy_type": "object", "metadata": None},
        ],
        "attributes": {},
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    tasks_table = pa.table({
        "task_index": pa.array(range(len(unique_tasks)), type=pa.int64()),
        _TASK_INDEX_COLUMN: pa.array(unique_tasks, type=pa.string()),
    }).replace_schema_metadata({"pandas": json.dumps(pandas_meta)})

    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": len(episodes),
        "total_frames": total,
        "total_tasks": len(unique_tasks),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_SIZE_MB,
        "video_files_size_in_mb": VIDEO_FILE_SIZE_MB,
        "fps": _json_fps(fps),
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": DATA_PATH_TEMPLATE,
        "video_path": None,
        "features": {name: f.to_json() for name, f in all_features.items()},
    }

    with atomic_dir(root) as staging:
        (staging / "meta").mkdir()
        (staging / INFO_PATH).write_text(json.dumps(info, indent=4))
        (staging / STATS_PATH).write_text(
            json.dumps({n: stats_json(s) for n, s in dataset_stats.items()}, indent=4))
        if extra_text is not None:
            (staging / EXTRA_PATH).write_text(extra_text)
        _write_table(tasks_table, staging / TASKS_PATH)
        _write_table(episodes_table, staging / EPISODES_PATH_TEMPLATE.format(chunk_index=0, file_index=0))
        _write_table(data_table, staging / DATA_PATH_TEMPLATE.format(chunk_index=0, file_index=0))


# =============================================================================== reading
def _load_json(path: Path, root: Path):
    if not path.is_file():
        raise PipelineInputError(path, None, f"missing: not a LeRobot v3.0 dataset at {root}")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise PipelineInputError(path, None, f"malformed JSON: {err}") from None


def _load_parquet(paths: list[Path], what: Path) -> pa.Table:
    if not paths:
        raise PipelineInputError(what, None, "missing: no parquet file found")
    tables = []
    for path in paths:
        try:
            tables.append(pq.read_table(path))
        except (pa.ArrowException, OSError) as err:
            raise PipelineInputError(path, None, f"unreadable parquet: {err}") from None
    try:
        return pa.concat_tables([t.replace_schema_metadata(None) for t in tables])
    except pa.ArrowException as err:
        raise PipelineInputError(what, None, f"parquet files disagree: {err}") from None


def _require(table: pa.Table, columns, path: Path) -> None:
    for column in columns:
        if column not in table.column_names:
            raise PipelineInputError(path, column, "missing column")


def _parse_features(raw, path: Path) -> dict[str, Feature]:
    if not isinstance(raw, dict) or not raw:
        raise PipelineInputError(path, "features", "must be a non-empty object")
    features = {}
    for name, spec in raw.items():
        where = f"features.{name}"
        if not isinstance(spec, dict) or "dtype" not in spec or "shape" not in spec:
            raise PipelineInputError(path, where, "needs 'dtype' and 'shape'")
        shape = spec["shape"]
        if not isinstance(shape, list) or not shape or not all(isinstance(s, int) and s > 0 for s in shape):
            raise PipelineInputError(path, f"{where}.shape", f"must be a list of positive ints, got {shape!r}")
        if spec["dtype"] not in SUPPORTED_DTYPES:
            raise PipelineInputError(path, f"{where}.dtype", f"unsupported dtype {spec['dtype']!r} (images/videos are not read here)")
        features[name] = Feature(spec["dtype"], tuple(shape), spec.get("names"))
    return features


def read_dataset(root) -> LeRobotData:
    """Reads a LeRobot v3.0 dataset (numeric features) into per-episode numpy arrays."""
    root = Path(root)
    if not root.is_dir():
        raise PipelineInputError(root, None, "missing: no dataset directory")
    info_path = root / INFO_PATH
    info = _load_json(info_path, root)
    if not isinstance(info, dict):
        raise PipelineInputError(info_path, None, "must be a JSON object")
    if info.get("codebase_version") != CODEBASE_VERSION:
        raise PipelineInputError(info_path, "codebase_version",
                                 f"expected {CODEBASE_VERSION!r}, got {info.get('codebase_version')!r}")
    fps = info.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise PipelineInputError(info_path, "fps", f"must be a positive number, got {fps!r}")
    all_features = _parse_features(info.get("features"), info_path)
    for name in INDEX_COLUMNS:
        if name not in all_features:
            raise PipelineInputError(info_path, f"features.{name}", "missing LeRobot index feature")
    features = {n: f for n, f in all_features.items() if n not in INDEX_COLUMNS}

    extra = None
    if (root / EXTRA_PATH).exists():
        extra = _load_json(root / EXTRA_PATH, root)
    if (root / STATS_PATH).exists():
        _load_json(root / STATS_PATH, root)  # optional for LeRobot; only checked for being JSON

    tasks_path = root / TASKS_PATH
    tasks_table = _load_parquet([tasks_path] if tasks_path.is_file() else [], tasks_path)
    task_column = _TASK_INDEX_COLUMN if _TASK_INDEX_COLUMN in tasks_table.column_names else "task"
    _require(tasks_table, ["task_index", task_column], tasks_path)
    task_of_index = dict(zip(tasks_table.column("task_index").to_pylist(), tasks_table.column(task_column).to_pylist()))

    episodes_dir = root / EPISODES_DIR
    episodes_table = _load_parquet(sorted(episodes_dir.glob("*/*.parquet")), episodes_dir)
    _require(episodes_table, ["episode_index", "tasks", "length", "dataset_from_index", "dataset_to_index"], episodes_dir)

    data_dir = root / DATA_DIR
    data_table = _load_parquet(sorted(data_dir.glob("*/*.parquet")), data_dir)
    _require(data_table, list(all_features), data_dir)
    index = column_values(data_table, "index", all_features["index"], data_dir).reshape(-1)
    order = np.argsort(index, kind="stable")
    data_table = data_table.take(pa.array(order))
    index = index[order]
    if not np.array_equal(index, np.arange(len(index))):
        raise PipelineInputError(data_dir, "index", "frame indices are not 0..N-1")
    values = {name: column_values(data_table, name, f, data_dir) for name, f in features.items()}
    episode_of_frame = column_values(data_table, "episode_index", all_features["episode_index"], data_dir).reshape(-1)
    task_of_frame = column_values(data_table, "task_index", all_features["task_index"], data_dir).reshape(-1)

    episodes, tasks = [], []
    rows = sorted(episodes_table.select(["episode_index", "tasks", "dataset_from_index", "dataset_to_index"]).to_pylist(),
                  key=lambda r: r["episode_index"])
    for row in rows:
        e, lo, hi = row["episode_index"], row["dataset_from_index"], row["dataset_to_index"]
        where = f"episode {e}"
        if not (0 <= lo < hi <= len(index)) or np.any(episode_of_frame[lo:hi] != e):
            raise PipelineInputError(episodes_dir, "dataset_from_index",
                                     f"{where}: frames {lo}:{hi} do not match the data's episode_index")
        frame_tasks = np.unique(task_of_frame[lo:hi])
        if len(frame_tasks) == 1 and int(frame_tasks[0]) in task_of_index:
            tasks.append(task_of_index[int(frame_tasks[0])])
        elif row["tasks"]:
            tasks.append("; ".join(row["tasks"]))
        else:
            raise PipelineInputError(tasks_path, "task_index", f"{where}: no task found")
        episodes.append({name: v[lo:hi] for name, v in values.items()})
    if not episodes:
        raise PipelineInputError(episodes_dir, "episode_index", "no episodes")
    if sum(len(next(iter(ep.values()))) for ep in episodes) != len(index):
        raise PipelineInputError(data_dir, "episode_index", "frames outside every episode")
    return LeRobotData(fps=float(fps), features=features, episodes=episodes, tasks=tasks, extra=extra, info=info)
