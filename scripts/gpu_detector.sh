#!/usr/bin/env bash
# The GPU machine's half of scripts/gpu_detector.py (its docstring): install the carried wheels,
# render the banks on the CPU cores, train the cpu detector for the minutes left before the
# deadline, and pack the run folder into $OUT (files of at most 15 MB).
#   bash scripts/gpu_detector.sh SECONDS   (the whole command's budget)
set -uo pipefail
start=$(date +%s)
deadline=$((start + ${1:-570}))
log() { echo "[$(( $(date +%s) - start )) s] $*"; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
python3 -c "import jax, flax, optax, grain, orbax.checkpoint as o; print(jax.__version__, flax.__version__, optax.__version__, jax.devices())" || exit 1
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
log "render banks on $(nproc) cores"
ids=$(python3 -c "import json; print(' '.join(sorted(json.load(open('.gpu/records/objects.json')), key=int)))")
workers=14
for k in $(seq 0 $((workers - 1))); do
  mine=$(echo $ids | tr ' ' '\n' | awk -v k=$k -v n=$workers 'NR % n == k' | tr '\n' ' ')
  JAX_PLATFORMS=cpu python3 -m datagen.banks --records .gpu/records --size 32 \
    --num-templates 512 --obj-ids $mine --quiet &
done
wait
log "banks: $(ls .gpu/records/banks | wc -l)"
left=$((deadline - $(date +%s) - 150))  # the step-time probe, compilation, packing
minutes=$(python3 -c "print(min(6.5, max(0.5, $left / 60)))")
log "train for $minutes minutes"
timeout -s TERM $((deadline - $(date +%s) - 30)) python3 scripts/gpu_detector.py train \
  --records .gpu/records --workdir /tmp/w/detector --minutes "$minutes" --batch-size 64 \
  --workers 12
log "trained (status $?)"
tar -C /tmp/w -cf - detector | split -b 15M - "$OUT/run.tar."
ls -la "$OUT"
log done
