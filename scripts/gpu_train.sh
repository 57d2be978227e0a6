#!/usr/bin/env bash
# One short training session on a lent GPU machine: three fine-tunes side by side on one device,
# each stopped at a wall-clock budget (`pcc train --max-minutes`, a `timeout` behind it), the
# checkpoints copied flat to OUT. Run from the repository root:
#
#     bash scripts/gpu_train.sh CARRY OUT
#
# CARRY (built by scripts/gpu_carry.sh; no rosbags / mcap / open3d / rclpy needed):
#   V_node/             SynthCars families, held-out seed, node crops: val split (true shapes) + train
#   A_det/              SynthCars families, simulated-detector boxes, node crops (training)
#   A_tight/            the same recordings, labelled boxes, tight crops (TraPCC's pseudo-GT pools)
#   real_node_*/        the 6 real KITTI object / nuScenes crops (as in the shipped runs)
#   synthA/meta.json    the SynthCars root the AML reference grids were voxelised from
#   aml_reference.npz   those grids (the prior's training shapes, all families)
#
# Jobs (background processes on the one GPU, modest CPU threads each):
#   a) PointPnCNet from the shipped weights, symmetric options, detector-box crops
#   b) TraPCC from the shipped weights, symmetric options, detector-box crops, family pools
#   c) AML: the prior fine-tuned on the families' shapes, then the observation encoder on it
# OUT receives at most 8 flat files: {pointpncnet,trapcc,aml}.{safetensors,json} (the best
# validated weights of each run), runs.tar.gz (logs, curves, last weights, the AML prior).
# Budgets (minutes) can be overridden: PNC_MIN, TRAPCC_MIN, PRIOR_MIN, ENCODER_MIN, DEVICE; JOBS picks
# the jobs (default "pnc trapcc aml").
set -u
CARRY=$(cd "${1:?usage: gpu_train.sh CARRY OUT}" && pwd)
OUT=$(mkdir -p "${2:?usage: gpu_train.sh CARRY OUT}" && cd "$2" && pwd)
DEVICE=${DEVICE:-cuda}
JOBS=" ${JOBS:-pnc trapcc aml} "
wants() { [[ "$JOBS" == *" $1 "* ]]; }
PIDS=()
PNC_MIN=${PNC_MIN:-4.6}
TRAPCC_MIN=${TRAPCC_MIN:-4.6}
PRIOR_MIN=${PRIOR_MIN:-2.2}
ENCODER_MIN=${ENCODER_MIN:-2.2}
ITER=${ITER:-6000}          # caps; the minute budgets end the runs first on any machine seen so far
AML_ITER=${AML_ITER:-4000}
VAL_EVERY=${VAL_EVERY:-400}
VAL_N=${VAL_N:-150}
WORK=${WORK:-$(mktemp -d)}
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=2 MKL_NUM_THREADS=2
PY=${PY:-python3}
W=pcc_ros/weights
START=$(date +%s)
log() { echo "[gpu_train +$(( $(date +%s) - START ))s] $*"; }
# timeout's budget for a job: its loop budget plus room for start-up, the final validation and
# saving; SIGINT (pcc train writes its resume checkpoint on Ctrl-C), SIGKILL 20 s later.
hard() { "$PY" -c "import sys; print(int(float(sys.argv[1]) * 60 + float(sys.argv[2])))" "$1" "$2"; }
train() { timeout -s INT -k 20 "$1" "$PY" -m pcc_ros.cli train "${@:2}"; }

log "carry $CARRY, work $WORK, out $OUT, device $DEVICE"
nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv,noheader 2>/dev/null || true
# AML's completions (its validation) need scikit-image's marching cubes; without it the encoder
# trains unvalidated and its last weights are the result.
AML_VAL=96
"$PY" -c "import skimage" 2>/dev/null || { AML_VAL=0; log "scikit-image missing: AML encoder without validation"; }
REAL=(--real-data "$CARRY/real_node_kitti_object" --real-data "$CARRY/real_node_nuscenes_mini")
HELD='held_out=["../shared/data/kitti_tracking"]'

# a) PointPnCNet: node-crop inputs, tight targets (target_margin 0), mirror targets, flips, symmetry term.
wants pnc && (
  train "$(hard "$PNC_MIN" 75)" pointpncnet --data "$CARRY/V_node" --out "$WORK/pnc" --init $W/pointpncnet.safetensors \
    --device "$DEVICE" --threads 2 --no-progress --iterations "$ITER" --lr 1e-4 --lr-decay-every 2000 --batch-size 32 \
    --seed 3 --option views=2 --option loss_points=192 --option input_points=512 --option box_aspect=true \
    --option mirror_targets=true --option flip_prob=0.5 --option symmetry_weight=1.0 --option target_margin=0 \
    --option target_ground_margin=0.1 --option "$HELD" --real-data "$CARRY/A_det" "${REAL[@]}" --real-share 0.9 \
    --val-every "$VAL_EVERY" --checkpoint-every "$VAL_EVERY" --val-instances "$VAL_N" --select-by cd_l1 \
    --max-minutes "$PNC_MIN"
  echo "exit $?"
) > "$WORK/pnc.log" 2>&1 &
wants pnc && PIDS+=($!)

# b) TraPCC: the same inputs; pools from the families' tight crops (built here, ~15 s).
wants trapcc && (
  train "$(hard "$TRAPCC_MIN" 75)" trapcc --data "$CARRY/V_node" --out "$WORK/trapcc" --init $W/trapcc.safetensors \
    --device "$DEVICE" --threads 2 --no-progress --iterations "$ITER" --lr 1e-4 --lr-decay-every 2000 --batch-size 16 \
    --seed 3 --option "real_data=[\"$CARRY/A_det\",\"$CARRY/real_node_kitti_object\",\"$CARRY/real_node_nuscenes_mini\"]" \
    --option real_share=0.85 --option "pool_data=[\"$CARRY/A_tight\"]" --option "gt_dir=\"$WORK/trapcc_gt\"" \
    --option box_aspect=true --option input_points=256 --option "$HELD" --option mirror_targets=true \
    --option symmetry_weight=1.0 --val-every "$VAL_EVERY" --checkpoint-every "$VAL_EVERY" --val-instances "$VAL_N" \
    --max-minutes "$TRAPCC_MIN"
  echo "exit $?"
) > "$WORK/trapcc.log" 2>&1 &
wants trapcc && PIDS+=($!)

# c) AML: prior (VAE) fine-tuned on the families' reference grids, then the encoder on that prior
#    (warm start from the shipped encoder, lambda fixed at the shipped 10: no sweep in this budget).
wants aml && (
  train "$(hard "$PRIOR_MIN" 60)" aml --stage prior --data "$CARRY/synthA" --out "$WORK/aml_prior" --init $W/aml.safetensors \
    --device "$DEVICE" --threads 3 --no-progress --iterations "$AML_ITER" --lr 5e-4 --lr-decay-every 1500 --batch-size 16 \
    --seed 3 --option "reference_cache=\"$CARRY/aml_reference.npz\"" --val-every 500 --checkpoint-every 500 \
    --max-minutes "$PRIOR_MIN"
  echo "prior exit $?"
  if [ -f "$WORK/aml_prior/aml.safetensors" ]; then
    train "$(hard "$ENCODER_MIN" 60)" aml --stage encoder --data "$CARRY/V_node" --out "$WORK/aml" --device "$DEVICE" \
      --threads 3 --no-progress --iterations "$AML_ITER" --lr 5e-4 --lr-decay-every 1500 --batch-size 16 --seed 3 \
      --option "prior=\"$WORK/aml_prior/aml.safetensors\"" --option "encoder_init=\"$W/aml.safetensors\"" \
      --option lam=10 --option "real=\"$CARRY/A_det,$CARRY/real_node_kitti_object,$CARRY/real_node_nuscenes_mini\"" \
      --option real_repeat=2 --val-every 500 --checkpoint-every 500 --val-instances "$AML_VAL" --max-minutes "$ENCODER_MIN"
    echo "encoder exit $?"
  fi
) > "$WORK/aml.log" 2>&1 &
wants aml && PIDS+=($!)

TICK=0
while kill -0 "${PIDS[@]}" 2>/dev/null; do  # true while any job runs
  sleep 5
  TICK=$((TICK + 1))
  [ $((TICK % 6)) -eq 0 ] && log "running: $(for f in pnc trapcc aml_prior aml; do [ -f "$WORK/$f/log.jsonl" ] && \
    printf '%s %s; ' "$f" "$(tail -n 1 "$WORK/$f/log.jsonl" | cut -c1-110)"; done)"
done
wait "${PIDS[@]}"
log "jobs done"
for f in $JOBS; do log "$f: $(grep -E '^(exit|prior exit|encoder exit)' "$WORK/$f.log" | tr '\n' ' ')"; done

# The eight files: each backend's selected weights flat, the rest in one archive.
copy() { [ -f "$1" ] && cp "$1" "$OUT/$2" && log "copied $2 ($(du -k "$1" | cut -f1) KiB)"; }
copy "$WORK/pnc/pointpncnet.safetensors" pointpncnet.safetensors; copy "$WORK/pnc/pointpncnet.json" pointpncnet.json
copy "$WORK/trapcc/trapcc.safetensors" trapcc.safetensors; copy "$WORK/trapcc/trapcc.json" trapcc.json
copy "$WORK/aml/aml.safetensors" aml.safetensors; copy "$WORK/aml/aml.json" aml.json
(
  # the selected weights are already flat in OUT; the archive keeps each run's last weights,
  # the AML prior, logs and curves (well under 16 MiB)
  cd "$WORK" && tar -czf "$OUT/runs.tar.gz" --exclude='resume.*' --exclude='trapcc_gt' \
    --exclude='pnc/pointpncnet.safetensors' --exclude='trapcc/trapcc.safetensors' --exclude='aml/aml.safetensors' \
    ./*.log pnc trapcc aml_prior aml 2>/dev/null
)
log "runs.tar.gz $(du -k "$OUT/runs.tar.gz" | cut -f1) KiB; OUT: $(ls "$OUT" | tr '\n' ' ')"
for f in $JOBS; do echo "== tail $f.log"; tail -n 6 "$WORK/$f.log" | cut -c1-300; done
