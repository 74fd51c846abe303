#!/usr/bin/env bash
# Every speed benchmark on a CUDA machine; JSON and logs into $OUT (the device tool's
# output folder). Run from the project root after the gpu-wheels install:
#   export PYTHONPATH=/tmp/site:$PWD; bash bench/gpu_suite.sh [part]
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
  run sim_speed 200 bench/sim_speed.py --device cuda
  run render_speed 120 bench/render_speed.py --device cuda
  run drivers_speed 120 bench/drivers.py --part speed --device cuda
  run bake_speed 150 bench/bake_speed.py --device cuda --gaussians 300000
fi
if [ "$part" = b ]; then
  run usd_write 120 bench/usd_write.py --device cuda --points 300000 --frames 30 --fmt instancer,splat,both
  run physics 120 bench/physics.py --quick --device cuda
  run fit_speed 300 bench/fit_speed.py --device cuda --gaussians 100000 --width 1024 --height 576
fi
