#!/usr/bin/env bash
# Trains a recipe of this folder on a lent GPU machine (the workplace's device tool), as the last call of
# a lease: see far_jump/README.md for the calls before it. In order:
#   1. installs the GPU kit (benchmarks/gpu_kit.sh);
#   2. benchmarks/env_throughput_gpu.py at 4096 worlds, eager and with env.compile: the GPU figures, and
#      a check that the compiled step runs on CUDA at all; if it fails, training goes on with
#      env.compile false (a copy of the recipe's params beside it);
#   3. both training stages with the recipe's params, each stopped by `timeout` if it would run past the
#      call's 600 s (the recipe's own wall-clock caps are sized to end well before).
# models/<task> comes back through $OUT as tar parts of at most 15 MiB, also when a stage fails or is
# stopped: models_<task>.tar.* holds the policies, metrics and histories, checkpoints_<task>.tar.* each
# stage's latest checkpoint (what --resume needs) when it fits in what $OUT brings back.
# GPU use is sampled every 5 s into $OUT/nvidia_smi.csv, the benchmark's output is $OUT/env_throughput_gpu.txt.
#
#   bash models/pretrained/device_train.sh PARAMS TASK [--resume]
#
# Needs: the outputs of the data stages that training reads carried (data/{keyframes,push_prior}/TASK),
# the GPU kit's parts stashed or carried (benchmarks/gpu_kit.sh), and $OUT.
set -uo pipefail

params=${1:?usage: device_train.sh PARAMS TASK [--resume]}
task=${2:?usage: device_train.sh PARAMS TASK [--resume]}
resume=${3:-}
: "${OUT:?device_train.sh writes to \$OUT, which the device tool sets}"
deadline=$((SECONDS + 570))  # the device tool kills a call at 600 s, and the tar below needs a few

bring_back() {  # $OUT takes 8 files of 16 MiB, 64 MiB in all: the policies first, then what --resume needs
    [ -d "models/$task" ] || return
    local latest=() room
    (cd models && find "$task" -path '*/checkpoints' -prune -o -type f -print) > "$OUT/.policies"
    tar -C models -cf - -T "$OUT/.policies" | split -b 15M -d - "$OUT/models_$task.tar."
    for pointer in "models/$task"/*/*/checkpoints/latest; do
        [ -f "$pointer" ] && latest+=("${pointer#models/}" "$(dirname "${pointer#models/}")/$(cat "$pointer")")
    done
    room=$(( (60 << 20) - $(cat "$OUT"/models_"$task".tar.* | wc -c) ))
    [ ${#latest[@]} -gt 0 ] && tar -C models -cf "$OUT/.checkpoints.tar" "${latest[@]}"
    if [ ! -f "$OUT/.checkpoints.tar" ]; then
        echo "[device_train] no checkpoint yet: policies only"
    elif [ "$(stat -c %s "$OUT/.checkpoints.tar")" -le "$room" ]; then
        split -b 15M -d "$OUT/.checkpoints.tar" "$OUT/checkpoints_$task.tar."
    else
        echo "[device_train] the latest checkpoints do not fit in what \$OUT brings back: policies only"
    fi
    rm -f "$OUT/.policies" "$OUT/.checkpoints.tar"
    ls -la "$OUT"
}
trap bring_back EXIT

phase() { echo "[device_train] $(date +%T) $*"; }

phase "installing the GPU kit"
bash benchmarks/gpu_kit.sh install || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 5 > "$OUT/nvidia_smi.csv" 2>&1 &

phase "env throughput on the GPU, eager and compiled"
timeout 180 python3 benchmarks/env_throughput_gpu.py --worlds 4096 --steps 50 > "$OUT/env_throughput_gpu.txt" 2>&1
bench=$?
tail -4 "$OUT/env_throughput_gpu.txt"
if [ $bench -ne 0 ] && [ $bench -ne 124 ] && grep -q "compile: true" "$params"; then
    eager="$(dirname "$params")/params_eager.yaml"
    sed 's/^\( *\)compile: true/\1compile: false/' "$params" > "$eager"
    phase "the benchmark failed (exit $bench): training with env.compile false ($eager)"
    params=$eager
fi

for stage in train_stage1 train_stage2; do
    left=$((deadline - SECONDS))
    phase "$stage ($left s left in this call)"
    timeout "$left" python3 "stages/$stage.py" --params "$params" --task "$task" --variant adamimic $resume || exit 1
done
phase "done"
