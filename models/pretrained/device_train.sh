#!/usr/bin/env bash
# Trains a recipe of this folder on a lent GPU machine (the workplace's device tool), as the last call of
# a lease: see far_jump/README.md for the calls before it. Both training stages run with the recipe's
# params; the whole models/<task> folder (policies, checkpoints, history) comes back through $OUT as tar
# parts of at most 15 MiB, also when a stage fails or the call runs out of time, so a later call or lease
# can go on with --resume. GPU use is sampled every 5 s into $OUT/nvidia_smi.csv.
#
#   bash models/pretrained/device_train.sh PARAMS TASK [--resume]
#
# Needs: the data stages' outputs for TASK carried (data/{human,retargeted,keyframes,push_prior}/TASK),
# the GPU kit's parts stashed or carried (benchmarks/gpu_kit.sh), and $OUT.
set -uo pipefail

params=${1:?usage: device_train.sh PARAMS TASK [--resume]}
task=${2:?usage: device_train.sh PARAMS TASK [--resume]}
resume=${3:-}
: "${OUT:?device_train.sh writes to \$OUT, which the device tool sets}"

bring_back() {
    if [ -d "models/$task" ]; then
        tar -C models -cf - "$task" | split -b 15M -d - "$OUT/models_$task.tar."
        ls -la "$OUT"
    fi
}
trap bring_back EXIT

bash benchmarks/gpu_kit.sh install || exit 1
export PYTHONPATH=/tmp/site PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 5 > "$OUT/nvidia_smi.csv" 2>&1 &

python3 stages/train_stage1.py --params "$params" --task "$task" --variant adamimic $resume || exit 1
python3 stages/train_stage2.py --params "$params" --task "$task" --variant adamimic $resume
