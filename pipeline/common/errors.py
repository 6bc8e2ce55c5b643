"""One error type for bad input, so every stage reports it the same way."""

from __future__ import annotations

from pathlib import Path


class PipelineInputError(ValueError):
    """Bad user input: names the file (or task) and the field that is wrong.

    Stages catch it at the top level, print the message alone (no traceback) and exit 2.
    """

    def __init__(self, source: str | Path, field: str | None, problem: str):
        self.source = str(source)
        self.field = field
        self.problem = problem
        where = f"{self.source}: {field}" if field else self.source
        super().__init__(f"{where}: {problem}")


def check_finite(array, source: str | Path, field: str) -> None:
    import numpy as np

    arr = np.asarray(array)
    if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise PipelineInputError(source, field, f"contains {bad} NaN/inf value(s)")


def check_shape(array, shape: tuple, source: str | Path, field: str) -> None:
    """`shape` may hold None for any length; raises naming the field on mismatch."""
    import numpy as np

    arr = np.asarray(array)
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape))
    if not ok:
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise PipelineInputError(source, field, f"expected shape {want}, got {tuple(arr.shape)}")
