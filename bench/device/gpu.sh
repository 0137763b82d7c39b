#!/usr/bin/env bash
# The project's GPU runs on a lent device machine, from the checkout root there, after
# ../shared/device/README.md has staged the wheels (its /tmp/fsw/env.sh, or $FSW_ENV, exists;
# stage with the extra name qdldl, which the machine lacks: ../shared/device/stage-gpu-wheels.sh qdldl):
#
#   bash bench/device/gpu.sh tests                  pytest -m gpu (Warp CUDA and OpenCL on the GPU)
#   bash bench/device/gpu.sh table NAME SCENE...    bench/paper_table.py on Warp CUDA
#   bash bench/device/gpu.sh study NAME SCENE...    bench/identifiability.py on Warp CUDA
#   bash bench/device/gpu.sh bench                  fsswarp bench: Warp CUDA, OpenCL on the GPU, PoCL on the host
#   bash bench/device/gpu.sh ab BEFORE AFTER [ARGS] bench/ab_reconstruct.py on Warp CUDA
#   bash bench/device/gpu.sh profile [ARGS]         bench/loop_profile.py on Warp CUDA
#   bash bench/device/gpu.sh grid [ARGS]            bench/grid_profile.py (the pose grid per launch size) on Warp CUDA
#   bash bench/device/gpu.sh demo [ARGS]            bench/demo_wall.py (the whole demo) on Warp CUDA
#   bash bench/device/gpu.sh batch [ARGS]           bench/batch_throughput.py (reconstructions at once) on Warp CUDA
#   bash bench/device/gpu.sh ray [ARGS]             bench/batch_ray.py (fsswarp batch on a local Ray) on Warp CUDA
#   bash bench/device/gpu.sh resident [ARGS]        bench/resident_jobs.py (a batch worker's jobs, fresh or resident) on Warp CUDA
#
# `ray` needs Ray, which the machine lacks: its cp312 wheel (79 MB) in two parts under 64 MiB and the
# wheels the machine lacks (jsonschema, jsonschema-specifications, referencing, rpds-py), each part
# carried by a call of its own, joined and installed with pip --no-deps --target /tmp/site.
# Records land in $OUT (the device tool brings them back), as under bench/records/: copy
# $OUT/reconstruction/NAME.json (table) and $OUT/identifiability/NAME.json (study) to the same
# folders there and each bench run's $OUT/bench-*/bench.json to bench/records/<machine>.json,
# then run `python bench/report.py`.
# The machine has no network and no hatchling, so the project runs from the checkout
# (PYTHONPATH), not installed.
set -euo pipefail
source "${FSW_ENV:-/tmp/fsw/env.sh}"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
out=${OUT:?OUT must name the folder that comes back}
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
fail() { echo "bench/device/gpu.sh: error: $1" >&2; exit 2; }
[ $# -gt 0 ] || fail "name a run: tests, table, study, bench, ab, profile, grid, demo, batch, ray or resident"
what=$1
shift
# The staged wheels are installed without byte code and the machine sets PYTHONDONTWRITEBYTECODE, so
# every process would compile trimesh, warp and fsswarp from source (~2.5 s of each command's start
# on an H200 host): compile them in place (once; later runs find them compiled), as pip does at a
# user's install.
site=$(python -c "import os, trimesh; print(os.path.dirname(os.path.dirname(trimesh.__file__)))" 2>/dev/null) &&
  python -m compileall -q -j 0 "$site" fsswarp >/dev/null 2>&1 || true
case "$what" in
  tests)
    python -m pytest -q -p no:cacheprovider -m gpu tests "$@" ;;
  table)
    [ $# -ge 2 ] || fail "table needs NAME and at least one SCENE"
    name=$1; shift
    python bench/paper_table.py --name "$name" --backend warp --device cuda:0 --records "$out/reconstruction" \
      --scenes "$@" ;;
  study)
    [ $# -ge 2 ] || fail "study needs NAME and at least one SCENE"
    name=$1; shift
    python bench/identifiability.py --name "$name" --backend warp --device cuda:0 --records "$out/identifiability" \
      --scenes "$@" ;;
  bench)
    families=raycast,synthesis,carving,pose,reconstruction
    python -m fsswarp --backend warp --device cuda:0 bench --out "$out/bench-warp-cuda" --families "$families" \
      --budget 10 --repeat 3
    python -m fsswarp --backend opencl --device nvidia bench --out "$out/bench-opencl-nvidia" --families "$families" \
      --budget 10 --repeat 3 --no-peers
    python -m fsswarp --backend opencl --device pocl bench --out "$out/bench-pocl" \
      --families raycast,synthesis,carving,pose --budget 3 --repeat 3 --no-peers ;;
  ab)
    python bench/ab_reconstruct.py "$@" --backend warp --device cuda:0 ;;
  profile)
    python bench/loop_profile.py --backend warp --device cuda:0 "$@" ;;
  grid)
    python bench/grid_profile.py --backend warp --device cuda:0 "$@" ;;
  demo)
    python bench/demo_wall.py "$@" -- --backend warp --device cuda:0 ;;
  batch)
    python bench/batch_throughput.py "$@" -- --backend warp --device cuda:0 ;;
  ray)
    python bench/batch_ray.py "$@" -- --backend warp --device cuda:0 ;;
  resident)
    python bench/resident_jobs.py "$@" -- --backend warp --device cuda:0 ;;
  *)
    fail "unknown run '$what' (tests, table, study, bench, ab, profile, grid, demo, batch, ray or resident)" ;;
esac
