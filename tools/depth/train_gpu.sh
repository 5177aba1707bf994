#!/usr/bin/env bash
# The SGBM-guided stereo network (services/depth/refine_net.py) on one GPU machine, in one go: render the layered
# training set on all its cores, then train two candidates side by side on the GPU, each fed by its own loader
# processes: "ft" fine-tunes the shipped weights, "scratch" starts from random weights. Whether one ships is decided on
# the layered validation split (non-occluded EPE) and the agreement with SGBM on the real EuRoC frames (`sigmaslam
# eval stereo`), never on Middlebury, which is the test.
#
# Timing on an H200 machine (16 cores, stop 38): rendering ran at ~0.33 s per frame per core (280 s for 12 288 + 256
# frames on 15 processes; 2.5x slower per core than this project's 2-core Xeon), training at ~46 steps of 16 crops
# per second with 14 loader processes. The defaults (8192 frames, 5 minutes each) fit one 10-minute device call.
#
#   tools/depth/train_gpu.sh REAL_DIR OUT_DIR [TRAIN_FRAMES] [MINUTES]
#
# REAL_DIR holds the unlabelled photographs used as materials (eth3d_two_view/, euroc_V1_01_micro/; the layout of
# $SIGMASLAM_SHARED/data/real). OUT_DIR receives both candidates' .pt/.json/.curve.csv and dataset.json; the logs
# stay in the data folder (their ends are printed).
set -euo pipefail
real=$1
out=$2
frames=${3:-8192}
minutes=${4:-5}
data=${STEREO_DATA:-/tmp/stereo_train}
cores=$(nproc)
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
"$py" -c "import torch; print('torch', torch.__version__, torch.cuda.is_available() and torch.cuda.get_device_name())"
"$py" -m tools.depth.make_stereo_data --out "$data" --train "$frames" --val 256 --seed 0 \
    --workers $((cores - 1)) --real "$real" > "$data.render.log" 2>&1
tail -1 "$data.render.log"
cp "$data/dataset.json" "$out/"
workers=$(((cores - 2) / 2))
common=(--net stereo_refine --data "$data" --crop 256 320 --batch 16 --minutes "$minutes"
        --max-wall-minutes "$minutes" --loader-workers "$workers" --checkpoint-minutes 0 --seed 0)
"$py" -m tools.depth.train "${common[@]}" --init services/depth/weights/stereo_refine.pt --lr 5e-4 \
    --out "$out/stereo_refine_ft" > "$data.ft.log" 2>&1 &
"$py" -m tools.depth.train "${common[@]}" --lr 1e-3 --out "$out/stereo_refine_scratch" \
    > "$data.scratch.log" 2>&1 &
wait
tail -n 2 "$data.ft.log" "$data.scratch.log"
