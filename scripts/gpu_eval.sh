#!/usr/bin/env bash
# Score the checkpoints a GPU session returned (scripts/gpu_train.sh) against the shipped ones, on
# this machine (CPU), on data none of them trained on:
#   1. real KITTI tracking 0000 (`pcc eval --real`, labelled boxes): published and generated-only
#      completeness, the unseen half, lateral balance, consistency; the three-view PNG;
#   2. the same frames with PointRCNN's boxes, and the observations it matched with the labels' boxes
#      (what the detector's box errors cost each weights);
#   3. SynthCars families, held-out seed 21 (true shapes): generated points and the published
#      output (crop + generated, decode_density 2), per family;
#   4. `pcc demo` on SynthCars seeds (the node on the simulated detector's boxes vs true shapes);
#   5. scripts/gpu_compare.py: old vs new per backend, and whether the ship gate holds;
#   6. steps 1-2 on the mirrored frames (`--real-mirror`: both real tracks are seen from their left;
#      mirrored, from their right), reported by gpu_compare.py beside the gate, not part of it
#      (run before step 5 to see them: STEPS="1 2 3 4 6 5").
#
#     bash scripts/gpu_eval.sh RETURNED OUTDIR [FAMILY_CACHE]
#
# RETURNED: the folder holding {pointpncnet,trapcc,aml}.{safetensors,json}; a missing one is
# skipped. FAMILY_CACHE (default OUTDIR/fam_cache) is built once if absent. The shipped weights'
# runs are reused when OUTDIR already holds them (their .json / demo log). Environment: PY,
# SEEDS (demo seeds, default "2026 2027 2028"; empty: no demo), STEPS (default "1 2 3 4 6 5"), WHICH,
# BACKENDS (default input,mirror,pointpncnet,trapcc,aml; e.g. input,mirror,pointpncnet scores one
# learned backend, its shipped runs reused from OUTDIR).
set -u
RET=$(cd "${1:?usage: gpu_eval.sh RETURNED OUTDIR [FAMILY_CACHE]}" && pwd)
OUTD=${2:?usage: gpu_eval.sh RETURNED OUTDIR [FAMILY_CACHE]}
FAM=${3:-$OUTD/fam_cache}
PY=${PY:-python3}
SEEDS=${SEEDS-2026 2027 2028}
STEPS=${STEPS:-1 2 3 4 6 5}
WHICH=${WHICH:-shipped new}  # "shipped": precompute the reference runs alone
P="$PY -m pcc_ros.cli"
mkdir -p "$OUTD"
CK=()
NEW=()
for b in pointpncnet trapcc aml; do
  if [ -f "$RET/$b.safetensors" ] && [ -f "$RET/$b.json" ]; then
    CK+=(--checkpoint "$b=$RET/$b.safetensors"); NEW+=("$b")
  else
    echo "no returned $b checkpoint in $RET: shipped only"
  fi
done
BACKENDS=${BACKENDS:-input,mirror,pointpncnet,trapcc,aml}
LEARNED=()
for b in pointpncnet trapcc aml; do [[ ",$BACKENDS," == *",$b,"* ]] && LEARNED+=("$b"); done
REAL=(--real --real-sources ../shared/data/kitti_tracking,../shared/data/nuscenes_mini --backends "$BACKENDS")
DET=(--real --real-sources ../shared/data/kitti_tracking --backends "$BACKENDS"
     --real-detections ../shared/data/kitti_tracking/detections/pointrcnn)
PLOT=$(for b in "${LEARNED[@]}"; do printf '%s,%s/generated,' "$b" "$b"; done)
PLOT=${PLOT%,}
step() { [[ " $STEPS " == *" $1 "* ]]; }
done_before() { [ "$1" = shipped ] && [ -s "$2" ]; }  # a shipped run already in OUTDIR

if step 1; then
  for w in $WHICH; do
    extra=(); [ $w = new ] && extra=("${CK[@]}")
    done_before $w "$OUTD/real_$w.json" || $P eval "${REAL[@]}" "${extra[@]}" --real-table "$OUTD/real_$w.md" --json "$OUTD/real_$w.json" \
      --plot "$OUTD/real_$w.png" --plot-backends "$PLOT" > "$OUTD/real_$w.log" 2>&1
    echo "== real, labelled boxes, $w (exit $?)"; cat "$OUTD/real_$w.md"
  done
fi
if step 2; then
  for w in $WHICH; do
    extra=(); [ $w = new ] && extra=("${CK[@]}")
    done_before $w "$OUTD/real_det_$w.json" || $P eval "${DET[@]}" "${extra[@]}" --real-table "$OUTD/real_det_$w.md" \
      --json "$OUTD/real_det_$w.json" > "$OUTD/real_det_$w.log" 2>&1
    echo "== real, PointRCNN boxes, $w (exit $?)"; cat "$OUTD/real_det_$w.md"
    [ $w = shipped ] && continue  # shipped: docs/results/eval-real-matched-labels.json
    $P eval "${DET[@]}" "${extra[@]}" --real-matched-labels \
      --real-table "$OUTD/real_pair_$w.md" --json "$OUTD/real_pair_$w.json" > "$OUTD/real_pair_$w.log" 2>&1
    echo "== real, PointRCNN's matches with the labels' boxes, $w (exit $?)"; cat "$OUTD/real_pair_$w.md"
  done
fi
if step 3; then
  if [ ! -f "$FAM/index.json" ]; then  # the held-out families set of docs/evaluation.md
    $P synth --out "$FAM.synth" --sequences 4 --frames 20 --seed 21 --test-fraction 0.99 \
      --vehicle-mix sedan=1,hatchback=1,estate=1,suv=1,van=1,pickup=1,truck=1 > "$OUTD/fam_synth.log" 2>&1
    $P extract "$FAM.synth" --out "$FAM" --node-crop --classes Car,Van,Truck --no-progress > "$OUTD/fam_extract.log" 2>&1
  fi
  for w in $WHICH; do
    extra=(); [ $w = new ] && extra=("${CK[@]}")
    done_before $w "$OUTD/fam_gen_$w.json" || $P eval --data "$FAM" --split test --backends "$BACKENDS" "${extra[@]}" --max-instances 350 --no-emd --seed 0 \
      --no-gt-free --json "$OUTD/fam_gen_$w.json" > "$OUTD/fam_gen_$w.log" 2>&1
    echo "== SynthCars families (seed 21), generated points, $w (exit $?)"
    grep -A12 -iE "by family|lateral|unseen" "$OUTD/fam_gen_$w.log" | head -60
    done_before $w "$OUTD/fam_pub_$w.json" || $P eval --data "$FAM" --split test --backends "$(IFS=,; echo "${LEARNED[*]}")" \
      "${extra[@]}" --max-instances 350 --no-emd \
      --seed 0 --no-gt-free --keep-input --decode-density 2 --json "$OUTD/fam_pub_$w.json" > "$OUTD/fam_pub_$w.log" 2>&1
    echo "== SynthCars families, published output (crop + generated, density 2), $w (exit $?)"
  done
fi
if step 4; then
  for s in $SEEDS; do
    for b in "${LEARNED[@]}"; do
      for w in $WHICH; do
        extra=()
        if [ $w = new ]; then
          [[ " ${NEW[*]} " == *" $b "* ]] || continue
          extra=(--checkpoint "$RET/$b.safetensors")
        fi
        done_before $w "$OUTD/demo_${s}_${b}_$w/demo.json" || $P demo --seed "$s" --backend "$b" --baselines "" \
          "${extra[@]}" --out "$OUTD/demo_${s}_${b}_$w" > "$OUTD/demo_${s}_${b}_$w.log" 2>&1
        echo "== demo seed $s $b $w (exit $?): $(grep -E "^$b " "$OUTD/demo_${s}_${b}_$w.log" | head -1)"
      done
    done
  done
fi
if step 6; then
  for w in $WHICH; do
    extra=(); [ $w = new ] && extra=("${CK[@]}")
    done_before $w "$OUTD/real_mirror_$w.json" || $P eval "${REAL[@]}" "${extra[@]}" --real-mirror \
      --real-table "$OUTD/real_mirror_$w.md" --json "$OUTD/real_mirror_$w.json" > "$OUTD/real_mirror_$w.log" 2>&1
    echo "== real, labelled boxes, mirrored frames, $w (exit $?)"; cat "$OUTD/real_mirror_$w.md"
    done_before $w "$OUTD/real_det_mirror_$w.json" || $P eval "${DET[@]}" "${extra[@]}" --real-mirror \
      --real-table "$OUTD/real_det_mirror_$w.md" --json "$OUTD/real_det_mirror_$w.json" > "$OUTD/real_det_mirror_$w.log" 2>&1
    echo "== real, PointRCNN boxes, mirrored frames, $w (exit $?)"; cat "$OUTD/real_det_mirror_$w.md"
  done
fi
if step 5 && [[ " $WHICH " == *" new "* ]]; then
  $PY "$(dirname "$0")/gpu_compare.py" "$OUTD"
fi
