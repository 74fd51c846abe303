#!/usr/bin/env bash
# The GPU benchmarks on a CUDA machine, speed (parts a, b), accuracy (c-f), the 3 mm plant's fit, CLI and Pareto (g, h), the profiles and capture bakes (i), the thin and 1M-10M bakes (j), batch over GPUs (k), and the fit against a split reference
# with the drivers a cell it needs (l, m), and on a finer fit model with the whole-clip losses (n) and with E
# from the field alone or warm-started from it (o), the fast path under per-kernel compile
# options (p), and whether each row's reference is converged (q, r); JSON and logs
# into $OUT (the device tool's output folder). Run from the project root after the gpu-wheels
# install:
#   export PYTHONPATH=/tmp/site:$PWD; DATA=/tmp/data bash bench/gpu_suite.sh [part]
set -u
OUT=${OUT:-/tmp/gpu-out}
mkdir -p "$OUT"
export PYTHONPATH=/tmp/site:$PWD
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader > "$OUT/gpu.txt" 2>&1
run() {
  local name=$1 limit=$2; shift 2
  local t0=$(date +%s)
  timeout "$limit" python "$@" --json "$OUT/$name.json" > "$OUT/$name.log" 2>&1
  echo "$name rc=$? $(( $(date +%s) - t0 ))s"
}
part=${1:-a}
if [ "$part" = a ]; then
  run sim_speed 240 bench/sim_speed.py --device cuda --frame-cost
  run render_speed 120 bench/render_speed.py --device cuda
  run drivers_speed 120 bench/drivers.py --part speed --device cuda
  run bake_speed 150 bench/bake_speed.py --device cuda --gaussians 300000
fi
if [ "$part" = b ]; then
  run usd_write 120 bench/usd_write.py --device cuda --points 300000 --frames 30 --fmt instancer,splat,both
  run physics 120 bench/physics.py --quick --device cuda
  run fit_speed 300 bench/fit_speed.py --device cuda --gaussians 100000 --width 1024 --height 576
  run fit_speed_recompute 300 bench/fit_speed.py --device cuda --gaussians 100000 --width 1024 --height 576 --recompute
fi
# accuracy against converged references (docs/benchmarks.md, "Convergence against a fine
# reference" and "Fitted materials at another quality"); each part fits one 10-minute call.
# DATA: the folder holding udon.ply, donut_fused.ply and tree_100k.splat
DATA=${DATA:-../shared/data}
CONV="bench/convergence.py --device cuda --data $DATA"
if [ "$part" = c ]; then
  run convergence_udon 120 $CONV --gaussians 100000 --reference 192 --check-grid 256 --sweep 32,48,96,128 --scenes udon
  run convergence_donut 200 $CONV --gaussians 100000 --reference 128 --check-grid 192 --sweep 32,48,96 --scenes donut
  run convergence_tree 280 $CONV --gaussians 100000 --reference 192 --check-grid 256 --sweep 32,48,96,128 --scenes tree
fi
if [ "$part" = d ]; then
  run convergence_strip_1cm 560 $CONV --gaussians 300000 --reference 128 --check-grid 256 --scenes strip
fi
if [ "$part" = e ]; then
  run convergence_plant 300 $CONV --gaussians 300000 --reference 192 --check-grid 256 --sweep 32,48,64,96 --scenes plant
  run convergence_plant100k 250 $CONV --gaussians 100000 --reference 192 --check-grid 256 --sweep 32,48,96,128 --scenes plant
fi
# one process at a time (three at once did not finish a scene in 8 minutes)
if [ "$part" = f ]; then
  run quality_transfer_plant 280 bench/quality_transfer.py --device cuda --gaussians 100000 --scenes plant
  run quality_transfer_real 300 bench/quality_transfer.py --device cuda --gaussians 100000 --scenes tree,donut,udon --data $DATA
fi
# the fit and the CLI on the plant with 3 mm leaves (docs/benchmarks.md, "Fit"), two seeds a call
if [ "$part" = g ]; then
  run end_to_end_thin 200 bench/end_to_end.py --device cuda --gaussians 100000 --size 1024
  for s in 0 1; do
    run fit_recovery_thin_seed$s 180 bench/fit_recovery.py --device cuda --gaussians 100000 --views 2 --no-variants --set seed=$s
  done
fi
# bake time against error on the plant with 3 mm leaves: 300k Gaussians, so that its 192-cell
# reference is dense enough (at 100k, a 256-cell check moves unlike it); drivers built on the GPU,
# the CPU's part of the setup on 16 threads
if [ "$part" = h ]; then
  run pareto_thin 560 bench/pareto.py --device cuda --gaussians 300000 --threads 16 --grids 32,48,64,96,128 \
    --cfls 0.5 --ratios 0.05,0.1,0.5 --reference-grid 192 --reference-cfl 0.25 --reference-ratio 1.0 --check-grid 256 \
    --reference-cache /tmp/pareto_thin_ref.npz --png "$OUT/pareto_thin.png"
fi
# where a bake's substep goes (the thin plant and the captures) and the captures' bake speed
# and memory (docs/benchmarks.md, "Bake speed"; docs/simulator.md, the per-kernel profiles)
if [ "$part" = i ]; then
  run sim_profile_thin 120 bench/sim_profile.py --device cuda --scene thin --gaussians 300000
  run sim_profile_backward 120 bench/sim_profile.py --device cuda --sizes 100000:64 --backward
  for s in tree donut udon; do
    run sim_profile_$s 120 bench/sim_profile.py --device cuda --scene $s --gaussians 100000 --data $DATA
    run bake_speed_$s 150 bench/bake_speed.py --device cuda --scene $s --gaussians 300000 --data $DATA
  done
fi
# the bake at 300k with 3 mm leaves, and 1M-10M Gaussians (docs/benchmarks.md, "Bake speed":
# setup, wall, memory, the largest scene)
if [ "$part" = j ]; then
  run bake_speed_thin 150 bench/bake_speed.py --device cuda --gaussians 300000 --thin
  for n in 1000000 3000000 10000000; do
    run bake_scale_$n 300 bench/bake_speed.py --device cuda --gaussians $n --thin
  done
fi
# pdtool batch over every GPU of the machine against one (needs 2 or more GPUs; docs/batch.md)
if [ "$part" = k ]; then
  run batch_gpus 400 bench/batch_throughput.py --device cuda --workers 1 --gpus 1,$(nvidia-smi -L | wc -l) \
    --gaussians 100000 --quality default --frames 15
fi
# the fit against a split, converged reference (docs/benchmarks.md, "Fit against a converged
# truth") and the drivers a cell a bake needs ("Driving particles")
if [ "$part" = l ]; then
  run fit_truth_reference 200 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA --fields smooth \
    --reference-only --reference 128 --check-reference 192 --scene-gaussians donut=50000
  run driver_density 300 bench/driver_density.py --device cuda --gaussians 20000 --grids 64,128 --reference 192 \
    --data $DATA --scenes plant,tree,udon
  run driver_density_donut50k 200 bench/driver_density.py --device cuda --gaussians 50000 --grids 64,128 \
    --reference 192 --data $DATA --scenes donut
fi
# one field's rows: FIELD=smooth|region|random, SCENES (about 1.5-4 minutes a scene)
if [ "$part" = m ]; then
  run fit_truth_${FIELD:-smooth} 580 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA \
    --fields ${FIELD:-smooth} --scenes ${SCENES:-plant,tree,donut} --scene-gaussians donut=50000
fi
if [ "$part" = n ]; then  # the fit on 64 cells with 8 drivers a cell, and whether its loss prefers the truth
  run fit_truth_fit64_${FIELD:-smooth} 580 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA \
    --fields ${FIELD:-smooth} --scenes ${SCENES:-plant,tree} --scene-gaussians donut=50000 \
    --bake-qualities default --fit-grid 64 --fit-floor 8 --losses
fi
# the same fit with E from the field alone (V=field), the field first and then the full fit
# warm-started from it (V=warm), the same with no stage-1 level and a weight decay of DECAY
# on the per-driver residuals (V=decay), or one fit of two rounds, the field alone and then
# the residuals on top of it under that decay (V=field_first); scenes one after another
# (three rows at once in separate processes fit on one H200: 113-133 of 143 GB; with
# V=field_first the donut's row, 50k Gaussians, and the tree's random field together did
# not finish in 435 s: run the donut alone)
if [ "$part" = o ]; then
  case "${V:-field}" in
    field) extra=(--set driver_residual=false --fit-args=--no-level) ;;
    warm) extra=(--warm-from-field) ;;
    decay) extra=(--warm-from-field --fit-args=--no-level --set residual_decay=${DECAY:-1}) ;;
    *) extra=("--fit-args=--rounds=2 --no-level" --set field_first=true --set residual_decay=${DECAY:-1}) ;;
  esac
  run fit_truth_fit64_${V:-field}_${FIELD:-smooth} 580 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA \
    --fields ${FIELD:-smooth} --scenes ${SCENES:-plant,tree} --scene-gaussians donut=50000 \
    --bake-qualities default --fit-grid 64 --fit-floor 8 "${extra[@]}"
fi
# is each row's reference converged? FIELD's rows against 192 cells (part l checks the smooth
# field), and the tree's FIELD against 256 cells and a 256-cell tree against 384, about 1.5 and 6
# minutes two fields at once on an H200 (docs/benchmarks.md,
# "Which goals can these references judge?"); SPLIT_MOST: sub-particles along a Gaussian's axes
if [ "$part" = q ]; then
  run fit_truth_reference_${FIELD:-region} 500 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA \
    --fields ${FIELD:-region} --scenes ${SCENES:-plant,tree,donut} --scene-gaussians donut=50000 \
    --reference-only --check-reference 192 --split-most ${SPLIT_MOST:-4}
fi
if [ "$part" = r ]; then
  run fit_truth_reference_tree256 300 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA \
    --scenes tree --fields ${FIELD:-region} --reference-only --check-reference 256 --split-most ${SPLIT_MOST:-4}
  run fit_truth_reference_tree384 500 bench/fit_truth.py --device cuda --gaussians 20000 --data $DATA \
    --scenes tree --fields ${FIELD:-region} --reference-only --reference 256 --check-reference 384 \
    --split-most ${SPLIT_MOST:-4}
fi
# the fast path's forward under warp's per-kernel compile options (bench/kernel_ptx.py
# --kernel-options): warp's grid-stride loop put back in every simulator module (shipped
# without it), register caps and launch bounds on the one-launch G2P + P2G (its blocks are
# 64 threads, gather.ROWS_BLOCK), each against the shipped build in the same call
LOOP="gather.*:grid_stride=1;kernels.*:grid_stride=1;adjoint.*:grid_stride=1;autograd.*:grid_stride=1"
if [ "$part" = p ]; then
  i=0
  for opts in "" "$LOOP" "gather.g2p2g_rows:cuda_max_registers=64" "gather.g2p2g_rows:cuda_max_registers=96" \
              "gather.g2p2g_rows:launch_bounds=64/16" ""; do
    run sim_speed_options_$i 120 bench/sim_speed.py --device cuda --sizes 100000:64,300000:128 --no-backward \
      --kernel-options "$opts"
    i=$((i + 1))
  done
fi
