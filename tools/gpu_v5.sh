#!/usr/bin/env bash
# Model v5's maps from scratch on a lent GPU (preset gpu-train-v5), as one device call of at
# most 10 minutes: the run's first call measures (batch size, precision, learning rate) and
# fixes the plan; every call trains on from the run's folder in git, tools/runs/gpu-v5
# (plan.json, progress.json and, while the run is in progress, intermediate.pt: float16 weights,
# checked against their record intermediate.json; Adam restarts on each new machine), and
# leaves in $OUT the files that folder keeps next (7 files, ~5.5 MB; docs/pixelwise.md).
#
#   device run:  bash tools/gpu_v5.sh 420            (timeout_s 600; carry .whl if needed)
#   then here:   .venv/bin/python tools/gpu_recipe.py keep FILES_AT tools/runs/gpu-v5
#                cnnps score FILES_AT/intermediate.pt ../shared/data/{diligent/ballPNG,diligent-crop8/*PNG} \
#                    --pixels 2000 --exclude-from-mean ballPNG --out tools/runs/gpu-v5/score_p2000.json
# (`keep` copies the JSON files and the weights while the run is in progress; once its plan
# is spent, the weights' record alone: their bytes stay in FILES_AT, outside git.)
#
# The run in git (one H200, BUDGET=360) has spent its plan: a call on it stops with one line;
# RUN=tools/runs/NAME starts another (docs/models.md, "On a GPU").
#
# TRAIN_SECONDS ($1, default 420) is this call's training time; the measurement adds about
# a minute on the run's first call. DEVICE=cpu (and small BATCHES, LR_STEPS) tries the
# script on a machine without a GPU (PYTHON=.venv/bin/python here).
set -euo pipefail
TRAIN_SECONDS=${1:-420}
DEVICE=${DEVICE:-cuda}
PYTHON=${PYTHON:-python3}
RUN=${RUN:-tools/runs/gpu-v5}
DATA_DIR=${DATA_DIR:-/root/gpu-v5}
BATCHES=${BATCHES:-4096 16384}
LRS=${LRS:-2e-3 4e-3}
LR_STEPS=${LR_STEPS:-100}
BUDGET=${BUDGET:-1500}  # the run's planned training seconds over all calls (fixes its steps and schedule)
: "${OUT:?OUT must name the folder whose files come back}"

export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
if compgen -G ".whl/*.whl" > /dev/null; then  # packages the machine lacks, brought as wheels
  "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD
fi
if [ "$DEVICE" = cuda ]; then nvidia-smi --query-gpu=name,memory.total --format=csv,noheader | tee "$OUT/gpu.txt"; fi

mkdir -p "$RUN"
MEASURE=$RUN/measure.json
if [ ! -f "$RUN/plan.json" ] && [ ! -f "$DATA_DIR/plan.json" ]; then
  # shellcheck disable=SC2086
  "$PYTHON" tools/gpu_recipe.py measure --preset gpu-train-v5 --device "$DEVICE" --out "$OUT" --seconds 3 \
      --batches $BATCHES --precisions bf16 --lrs $LRS --lr-steps "$LR_STEPS"
  MEASURE=$OUT/measure.json
elif [ -f "$MEASURE" ]; then
  cp "$MEASURE" "$OUT/measure.json"
fi
"$PYTHON" tools/gpu_recipe.py train --preset gpu-train-v5 --device "$DEVICE" --data-dir "$DATA_DIR" \
    --measure "$MEASURE" --restore "$RUN" --budget-seconds "$BUDGET" --seconds "$TRAIN_SECONDS" \
    --pack "$OUT" 2>&1 | tee "$OUT/train.log"
# what comes back is at most 8 files: the pieces of the whole state and model.pt stay behind
# (intermediate.pt holds the weights; the pieces matter only to a call on this warm machine)
rm -f "$OUT"/step-*.part* "$OUT/model.pt"
ls -l "$OUT"
