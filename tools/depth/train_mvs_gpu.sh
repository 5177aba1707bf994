#!/usr/bin/env bash
# The MVS network (services/depth/mvs_net.py) on one GPU machine, in one call: render the dressed multi-view set
# (tools/depth/make_dataset.py --dressed --left-only: material images, bars, near objects, varied focal length,
# camera effects) on the machine's cores while two candidates train on the GPU side by side and pick up the scenes
# as they are rendered: "ft" fine-tunes the shipped weights, "scratch" starts from random weights. The validation
# scenes are rendered first; each candidate's gain is fitted on them at the end (sec. V-A). Whether one ships is
# decided here, on the procedural test split and the replica (`sigmaslam eval depth`), never on Middlebury.
#
#   tools/depth/train_mvs_gpu.sh REAL_DIR OUT_DIR [MAX_TRAIN_SCENES] [MINUTES]
#
# REAL_DIR holds the unlabelled photographs used as materials (eth3d_two_view/, euroc_V1_01_micro/; the layout of
# $SIGMASLAM_SHARED/data/real). OUT_DIR receives both candidates' .pt/.json/.curve.csv and dataset.json (7 files);
# the logs stay beside the data folder and their ends are printed. Rendering stops when the training does;
# MAX_TRAIN_SCENES only bounds it. Stop 41 on an H100 (16 cores): 103 scenes rendered in 420 s, ~15 steps of 8 crops
# per second per candidate; `MVS_FIRST_SCENES=10 tools/depth/train_mvs_gpu.sh data/gpu_real OUT 1000 5.5` took 434 s.
set -euo pipefail
real=$1
out=$2
scenes=${3:-1000}
minutes=${4:-6}
frames=${MVS_FRAMES:-12}
val=${MVS_VAL_SCENES:-8}
first=${MVS_FIRST_SCENES:-16}
data=${MVS_DATA:-/tmp/mvs_train}
cores=$(nproc)
py=${PYTHON:-python3}
mkdir -p "$out" "$data"
export PYTHONUNBUFFERED=1
# one thread per process: 13 render processes each with a full BLAS/OpenCV pool ran ~15x slower (stop 41)
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
"$py" -c "import torch; print('torch', torch.__version__, torch.cuda.is_available() and torch.cuda.get_device_name())"
dressed=(--out "$data" --dressed --left-only --real "$real" --frames "$frames" --test 0)
# the validation scenes (needed only when the training ends) and the training scenes render side by side, each
# command in its own process group so that its pool stops with it below
setsid "$py" -m tools.depth.make_dataset "${dressed[@]}" --train 0 --val "$val" --workers "${MVS_VAL_WORKERS:-3}" \
    > "$data.val.log" 2>&1 < /dev/null &
render_val=$!  # done long before the trainers read the validation split at their end
sleep 2  # the two commands add their splits to one dataset.json, one after the other
setsid "$py" -m tools.depth.make_dataset "${dressed[@]}" --train "$scenes" --val 0 \
    --workers $(( cores > 6 ? cores - 4 : 1 )) > "$data.render.log" 2>&1 < /dev/null &
render=$!
until [ "$(find "$data/train" -name 'scene_?????.npz' 2>/dev/null | wc -l)" -ge "$first" ]; do
    kill -0 "$render" 2>/dev/null || { echo "rendering stopped early"; tail -5 "$data.render.log"; exit 1; }
    sleep 3
done
echo "$(find "$data/train" -name 'scene_?????.npz' | wc -l) training scenes rendered; training starts"
common=(--net mvs --data "$data" --crop 192 256 --batch "${MVS_BATCH:-8}" --minutes 10000 --max-wall-minutes "$minutes"
        --checkpoint-minutes 2 --seed 0)
"$py" -m tools.depth.train "${common[@]}" --init services/depth/weights/mvs.pt --lr 5e-4 --out "$out/mvs_ft" \
    > "$data.ft.log" 2>&1 &
ft=$!
"$py" -m tools.depth.train "${common[@]}" --lr 1e-3 --out "$out/mvs_scratch" > "$data.scratch.log" 2>&1 &
scratch=$!
wait "$ft" "$scratch" || true
kill -- -"$render" 2>/dev/null || true
wait "$render" "$render_val" 2>/dev/null || true
cp "$data/dataset.json" "$out/" 2>/dev/null || true
for c in mvs_ft mvs_scratch; do  # a finished candidate's snapshot is not needed (a device call returns 8 files at most)
    [ -f "$out/$c.pt" ] && rm -f "$out/${c}_partial.pt" "$out/${c}_partial.json"
done
echo "$(find "$data/train" -name 'scene_?????.npz' | wc -l) training scenes at the end"
tail -n 3 "$data.ft.log" "$data.scratch.log"
