"""`.npz` files whose bytes follow from the arrays alone.

`np.savez` stamps every member of the zip with the current time, so the same arrays saved twice
make two different files, and DVC reruns every stage that depends on one. Here each member is
stamped 1980-01-01 (zip's earliest date); `np.load` reads the result as it reads any `.npz`.
"""

from __future__ import annotations

import io
import zipfile
from typing import BinaryIO

import numpy as np

_FIXED_DATE = (1980, 1, 1, 0, 0, 0)


def savez_reproducible(handle: BinaryIO, **arrays) -> None:
    """Like `np.savez(handle, **arrays)` (uncompressed, no pickles), with fixed member timestamps."""
    with zipfile.ZipFile(handle, "w", compression=zipfile.ZIP_STORED) as archive:
        for name, value in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(value), allow_pickle=False)
            member = zipfile.ZipInfo(f"{name}.npy", date_time=_FIXED_DATE)
            member.external_attr = 0o644 << 16  # a regular file, readable by all (what unzip shows)
            archive.writestr(member, buffer.getvalue())
