"""One set of CPU kernels on every x86-64 machine, so a stage gives the same bytes from the same inputs.

Why: numpy's BLAS (OpenBLAS), numpy's own loops, torch's ATen kernels, MKL and oneDNN each pick at
start-up the widest code path the CPU offers (AVX-512 on one machine, AVX2 on the next). The paths
sum in different orders, so the last bits differ, and the retargeting's warm-started IK carries
those bits from frame to frame: the same clip retargeted on an AVX-512 EPYC and on an AVX2 one gave
two different datasets, and everything trained on them after that. Thread counts do not matter
there (the IK's matrices are small; tests/test_reproducibility.py checks it), the kernel choice does.

`pin_cpu_kernels()` sets the libraries' own switches to their AVX2 + FMA path, which every x86-64
CPU from 2013 on has (Intel Haswell, AMD Zen). It must run before numpy or torch is first imported,
because each library reads its switch once when it loads: `import pipeline` calls it, and every
stage script imports `pipeline` first. On a CPU without AVX2 + FMA, or not x86-64, it changes
nothing: such a machine computes other bits, and reproducing a figure there is not promised.

`ADAMIMIC_NATIVE_KERNELS=1` in the environment leaves every library on its own choice (what a
speed comparison of kernels would want).
"""

from __future__ import annotations

import getpass
import os
import platform
import sys
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

OPT_OUT = "ADAMIMIC_NATIVE_KERNELS"
# numpy's runtime-dispatched AVX-512 targets (numpy/_core: __cpu_dispatch__); disabling one the
# CPU lacks is a no-op, so the list is the same on every machine.
_NUMPY_AVX512 = "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"
PINNED_ENV = {
    "OPENBLAS_CORETYPE": "Haswell",         # numpy's and scipy's OpenBLAS: the AVX2 kernels and block sizes
    "NPY_DISABLE_CPU_FEATURES": _NUMPY_AVX512,  # numpy's vector loops (exp, sin, sums): their AVX2 versions
    "ATEN_CPU_CAPABILITY": "avx2",          # torch's vectorised CPU kernels
    "MKL_CBWR": "AVX2",                     # torch's MKL (matmul, linear): its reproducible AVX2 path
    "ONEDNN_MAX_CPU_ISA": "AVX2",           # torch's oneDNN primitives
}
_LIBRARIES = ("numpy", "torch", "scipy")


def cpu_has_avx2_fma(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """True on an x86-64 CPU that reports AVX2 and FMA (read from /proc/cpuinfo: importing numpy
    to ask would load the libraries before their switches are set)."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        text = cpuinfo.read_text()
    except OSError:
        return False
    for line in text.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            return {"avx2", "fma"} <= flags
    return False


def pin_cpu_kernels(environ: MutableMapping[str, str] | None = None, cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Sets PINNED_ENV in `environ` (default os.environ), over any value already there, so that a
    machine-wide OPENBLAS_CORETYPE cannot make one run differ from another. Returns whether it pinned.
    Libraries already imported keep the path they chose: call it before them."""
    environ = os.environ if environ is None else environ
    if environ.get(OPT_OUT, "") not in ("", "0") or not cpu_has_avx2_fma(cpuinfo):
        return False
    environ.update(PINNED_ENV)
    # torch.compile's on-disk kernel cache is not keyed on ATEN_CPU_CAPABILITY: a CPU kernel compiled
    # for the CPU's own ISA by an unpinned run was reused under the pin and computed NaNs. Pinned runs
    # therefore keep a cache of their own (unless one is named).
    environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(pinned_inductor_cache()))
    return True


def pinned_inductor_cache() -> Path:
    """Where pinned runs keep torch.compile's kernels: beside inductor's default, one per user."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (a bare container)
        user = str(os.getuid())
    return Path(tempfile.gettempdir()) / f"torchinductor_{user}_{PINNED_ENV['ATEN_CPU_CAPABILITY']}_pinned"


def loaded_too_early() -> list[str]:
    """The numeric libraries imported before the pin (their kernels are then the CPU's own)."""
    return [name for name in _LIBRARIES if name in sys.modules]


def kernel_report() -> dict:
    """What the loaded libraries actually run on: OpenBLAS's core, numpy's enabled AVX-512 targets,
    torch's ATen capability (imports numpy and torch)."""
    import ctypes
    import glob

    import numpy as np
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

    report: dict = {"numpy_avx512": [f for f in __cpu_dispatch__ if f.startswith("AVX512") and __cpu_features__[f]]}
    libs = glob.glob(str(Path(np.__file__).parent.parent / "numpy.libs" / "*openblas*"))
    report["openblas_core"] = None
    for lib in libs:
        handle = ctypes.CDLL(lib)  # the copy numpy already loaded
        for symbol in ("scipy_openblas_get_corename64_", "openblas_get_corename64_", "openblas_get_corename"):
            if hasattr(handle, symbol):
                function = getattr(handle, symbol)
                function.restype = ctypes.c_char_p
                report["openblas_core"] = function().decode()
                break
    import torch

    report["torch_capability"] = torch.backends.cpu.get_cpu_capability()
    return report
