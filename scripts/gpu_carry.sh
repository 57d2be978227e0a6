#!/usr/bin/env bash
# Build the folder scripts/gpu_train.sh trains from (a lent GPU machine receives <= 45 MiB):
# SynthCars with the vehicle families, crops from the simulated detector's boxes and from the
# labels, the AML prior's reference grids, and the 6 real KITTI object / nuScenes crops the
# shipped runs trained on (KITTI tracking, the real evaluation set, is not in it).
#
#     bash scripts/gpu_carry.sh BUILD CARRY      # BUILD: scratch for the full data (~600 MB)
#
# Seeds 31 (training) and 32 (validation) are neither the shipped runs' (7) nor the evaluations'
# (11, 21, the demo's 2026-2028). Observations are thinned to <= 256 points (160 for the pools'
# tight crops; scripts/thin_cache.py): training reads no more than that of a crop.
set -eu
BUILD=${1:?usage: gpu_carry.sh BUILD CARRY}
CARRY=${2:?usage: gpu_carry.sh BUILD CARRY}
PY=${PY:-python3}
P="$PY -m pcc_ros.cli"
MIX=sedan=2,hatchback=1,wagon=1,suv=1.5,van=1.5,pickup=1,truck=0.5
C="--classes Car,Van,Truck --no-progress"
mkdir -p "$BUILD/full" "$CARRY/synthA"
$P synth --out "$BUILD/synthA" --sequences 8 --frames 30 --seed 31 --test-fraction 0 --vehicle-mix $MIX
$P synth --out "$BUILD/synthV" --sequences 2 --frames 20 --seed 32 --test-fraction 0 --vehicle-mix $MIX
$P extract "$BUILD/synthV" --out "$BUILD/full/V_node" --node-crop --val-fraction 0.5 --test-fraction 0 $C
$P extract "$BUILD/synthA" --out "$BUILD/full/A_det" --boxes detections \
    --detections-dir "$BUILD/synthA/detections/synthetic" --node-crop --val-fraction 0 --test-fraction 0 $C
$P extract "$BUILD/synthA" --out "$BUILD/full/A_tight" --val-fraction 0 --test-fraction 0 $C
$PY scripts/thin_cache.py "$BUILD/full/A_det" "$CARRY/A_det" --max-points 256
$PY scripts/thin_cache.py "$BUILD/full/A_tight" "$CARRY/A_tight" --max-points 160 --shape-tracks 0
$PY scripts/thin_cache.py "$BUILD/full/V_node" "$CARRY/V_node" --max-points 256 --shape-split val --shape-tracks 20
for s in kitti_object nuscenes_mini; do
  $P extract "../shared/data/$s" --out "$CARRY/real_node_$s" --node-crop --val-fraction 0 --test-fraction 0 --no-progress
done
# The prior's reference grids (voxelised once here; keyed by meta.json's content, not the path).
cp "$BUILD/synthA/meta.json" "$CARRY/synthA/"
$P train aml --stage prior --data "$BUILD/synthA" --out "$BUILD/aml_ref" --iterations 2 --batch-size 4 --val-every 0 \
    --threads 1 --no-progress --device cpu --option "reference_cache=\"$CARRY/aml_reference.npz\""
du -sb "$CARRY"
