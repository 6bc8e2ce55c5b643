"""Bit-reproducibility of the CPU pipeline's first stages: the bundled sample imported and retargeted
in two separate processes, with different thread counts and with the BLAS kernel another CPU would
pick, writes the same bytes (datasets, quality report, reference arrays). Why it can differ at all,
and what pins it: pipeline/common/cpu_kernels.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import REPO_ROOT
from pipeline.common.cpu_kernels import (OPT_OUT, PINNED_ENV, cpu_has_avx2_fma, pin_cpu_kernels,
                                         pinned_inductor_cache)

# Runs in a fresh interpreter: `import pipeline` first, as every stage script does, so the kernel
# switches are set before numpy and torch load.
_RETARGET_SCRIPT = r"""
import json, sys
from pathlib import Path
import pipeline
import numpy as np
import torch
from pipeline.common.cpu_kernels import kernel_report
from pipeline.config import load_params
from pipeline.human.dataset import write_human
from pipeline.human.importers import load_human_motion
from pipeline.motion.dataset import write_motions
from pipeline.retarget.core import retarget

out, threads = Path(sys.argv[1]), int(sys.argv[2])
torch.set_num_threads(threads)
params = load_params(pipeline.REPO_ROOT / "params.yaml")
human = load_human_motion(pipeline.REPO_ROOT / "data/sample/far_jump_synthetic.npz")
human.name = "far_jump_sample"
write_human(out / "human", human)
motion, report = retarget(human, params.retarget, progress=False)
write_motions(out / "motion", [motion])
(out / "quality.json").write_text(json.dumps(report, indent=1, default=float))
(out / "reference").mkdir()
for key in ("root_pos", "root_quat", "joint_pos", "body_pos", "body_quat"):
    np.save(out / "reference" / f"{key}.npy", getattr(motion, key))
print(json.dumps(kernel_report()))
"""

needs_avx2 = pytest.mark.skipif(not cpu_has_avx2_fma(), reason="the kernels are pinned on x86-64 CPUs with AVX2 + FMA only")


def _retarget_in_subprocess(out: Path, threads: int, extra_env: dict[str, str]) -> dict[str, bytes]:
    env = {k: v for k, v in os.environ.items() if k not in PINNED_ENV and k != OPT_OUT}
    env.pop("PYTHONPATH", None)
    env.update({"OMP_NUM_THREADS": str(threads), "OPENBLAS_NUM_THREADS": str(threads),
                "MKL_NUM_THREADS": str(threads), **extra_env})
    out.mkdir(parents=True)
    result = subprocess.run([sys.executable, "-c", _RETARGET_SCRIPT, str(out), str(threads)], cwd=REPO_ROOT,
                            env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    files = {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    assert {"human/meta/info.json", "motion/data/chunk-000/file-000.parquet", "quality.json",
            "reference/joint_pos.npy"} <= set(files)
    return files


def _differing(a: dict[str, bytes], b: dict[str, bytes]) -> list[str]:
    assert sorted(a) == sorted(b)
    return [name for name in a if a[name] != b[name]]


@needs_avx2
def test_retarget_writes_the_same_bytes_across_threads_and_cpu_kernels(tmp_path):
    # The second process runs on one thread everywhere and asks OpenBLAS for the kernel an AVX-only
    # CPU would get (what a machine of another generation does by itself): the pin overrides it.
    first = _retarget_in_subprocess(tmp_path / "a", threads=2, extra_env={})
    second = _retarget_in_subprocess(tmp_path / "b", threads=1, extra_env={"OPENBLAS_CORETYPE": "Sandybridge"})
    assert _differing(first, second) == []


@needs_avx2
def test_without_the_pin_another_blas_kernel_changes_the_retargeting(tmp_path):
    """The control: the comparison above does see a kernel change when nothing pins the kernels
    (the motion's last bits move), so its pass is not vacuous."""
    native = {OPT_OUT: "1"}
    first = _retarget_in_subprocess(tmp_path / "a", threads=2, extra_env={**native, "OPENBLAS_CORETYPE": "Haswell"})
    second = _retarget_in_subprocess(tmp_path / "b", threads=2, extra_env={**native, "OPENBLAS_CORETYPE": "Sandybridge"})
    changed = _differing(first, second)
    assert "reference/joint_pos.npy" in changed and "motion/data/chunk-000/file-000.parquet" in changed
    assert not any(name.startswith("human/") for name in changed)  # the import has no BLAS-sized sums


def test_pin_sets_every_switch_and_overrides_a_machine_setting(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx avx2 fma avx512f\n")
    environ = {"OPENBLAS_CORETYPE": "SkylakeX"}
    if not cpu_has_avx2_fma(cpuinfo):
        pytest.skip("not an x86-64 machine")
    assert pin_cpu_kernels(environ, cpuinfo) is True
    cache = environ.pop("TORCHINDUCTOR_CACHE_DIR")  # compiled kernels apart from unpinned runs' ones
    assert cache == str(pinned_inductor_cache()) and cache.endswith("_avx2_pinned")
    assert environ == PINNED_ENV
    named = {"TORCHINDUCTOR_CACHE_DIR": str(tmp_path / "mine")}
    assert pin_cpu_kernels(named, cpuinfo) is True and named["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "mine")


def test_pin_leaves_a_cpu_without_avx2_and_the_opt_out_alone(tmp_path):
    old = tmp_path / "cpuinfo"
    old.write_text("processor\t: 0\nflags\t\t: fpu sse2 avx\n")
    environ: dict[str, str] = {}
    assert pin_cpu_kernels(environ, old) is False and environ == {}
    modern = tmp_path / "cpuinfo_modern"
    modern.write_text("flags\t\t: avx2 fma\n")
    environ = {OPT_OUT: "1"}
    assert pin_cpu_kernels(environ, modern) is False and environ == {OPT_OUT: "1"}
    assert cpu_has_avx2_fma(tmp_path / "missing") is False


def test_npz_bytes_follow_from_the_arrays_alone(tmp_path):
    import io
    import zipfile

    import numpy as np

    from pipeline.common.npz import savez_reproducible

    arrays = {"joint_offsets": np.linspace(0.0, 1.0, 12).reshape(3, 4), "joint_names": np.array(["a", "bc"])}
    first, second = io.BytesIO(), io.BytesIO()
    savez_reproducible(first, **arrays)
    savez_reproducible(second, **arrays)
    assert first.getvalue() == second.getvalue()
    assert {m.date_time for m in zipfile.ZipFile(first).infolist()} == {(1980, 1, 1, 0, 0, 0)}
    (tmp_path / "x.npz").write_bytes(first.getvalue())
    with np.load(tmp_path / "x.npz") as loaded:
        assert sorted(loaded.files) == sorted(arrays)
        for key, value in arrays.items():
            assert np.array_equal(loaded[key], value) and loaded[key].dtype == value.dtype
