"""One feature of a LeRobot v3.0 dataset as a parquet column and back, and its stats (pipeline/dataset/lerobot.py
documents the layout): what the writer and the reader agree on, column by column."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.common.errors import PipelineInputError

SUPPORTED_DTYPES = {"float32", "float64", "int32", "int64", "bool"}
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


@dataclass(frozen=True)
class Feature:
    dtype: str
    shape: tuple[int, ...]
    names: list[str] | dict | None = None

    def to_json(self) -> dict:
        return {"dtype": self.dtype, "shape": list(self.shape), "names": self.names}



def frame_column(values: np.ndarray, feature: Feature) -> pa.Array:
    """One feature's column, typed as LeRobot's `datasets` schema declares it."""
    value_type = pa.from_numpy_dtype(np.dtype(feature.dtype))
    flat = pa.array(np.ascontiguousarray(values, dtype=feature.dtype).reshape(-1), type=value_type)
    shape = tuple(feature.shape)
    if shape == (1,):
        return flat
    if len(shape) == 1:
        return pa.FixedSizeListArray.from_arrays(flat, shape[0])
    # Array2D/Array3D are stored by `datasets` as nested variable-length lists.
    nested, nested_type = flat, value_type
    for size in reversed(shape):
        nested = pa.FixedSizeListArray.from_arrays(nested, size)
        nested_type = pa.list_(nested_type)
    return nested.cast(nested_type)


def hf_feature(feature: Feature) -> dict:
    shape = tuple(feature.shape)
    if shape == (1,):
        return {"dtype": feature.dtype, "_type": "Value"}
    if len(shape) == 1:
        return {"feature": {"dtype": feature.dtype, "_type": "Value"}, "length": shape[0], "_type": "List"}
    return {"shape": list(shape), "dtype": feature.dtype, "_type": f"Array{len(shape)}D"}

def feature_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-feature stats: reduce over frames and all axes but the last."""
    arr = values.reshape(-1, values.shape[-1]) if values.ndim > 1 else values.reshape(-1, 1)
    as_float = arr.astype(np.float64)
    out = {
        "min": arr.min(axis=0),
        "max": arr.max(axis=0),
        "mean": as_float.mean(axis=0),
        "std": as_float.std(axis=0),
        "count": np.array([values.shape[0]], dtype=np.int64),
    }
    for key, q in QUANTILES.items():
        out[key] = np.quantile(as_float, q, axis=0)
    return out


def stats_json(stats: dict[str, np.ndarray]) -> dict:
    return {key: np.asarray(value).tolist() for key, value in stats.items()}


def column_values(table: pa.Table, name: str, feature: Feature, path: Path) -> np.ndarray:
    column = table.column(name).combine_chunks()
    if column.null_count:
        raise PipelineInputError(path, name, f"{column.null_count} null value(s)")
    flat = column
    while pa.types.is_list(flat.type) or pa.types.is_large_list(flat.type) or pa.types.is_fixed_size_list(flat.type):
        if flat.null_count:
            raise PipelineInputError(path, name, "null entries inside lists")
        flat = flat.flatten()
    try:
        values = flat.to_numpy(zero_copy_only=False).astype(feature.dtype, copy=False)
    except (pa.ArrowException, TypeError, ValueError) as err:
        raise PipelineInputError(path, name, f"not numeric: {err}") from None
    expected = len(table) * int(np.prod(feature.shape))
    if values.size != expected:
        raise PipelineInputError(path, name, f"{values.size} values for {len(table)} frames of shape {feature.shape}")
    values = values.reshape((len(table),) + tuple(feature.shape))
    if values.dtype.kind == "f" and not np.all(np.isfinite(values)):
        raise PipelineInputError(path, name, "contains NaN/inf")
    return values
