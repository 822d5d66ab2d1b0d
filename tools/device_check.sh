#!/usr/bin/env bash
# The GPU checks of one device session, prepared so that they fit one `run` call:
# the kernel tests on the GPU (against the same NumPy references as on the CPU), the
# reference workload with each search and with the raster form of kernel #1, the two forms
# of kernel #2's convolution, and the BVH build options.
#
#   PERCH_WARP_COMMIT=<sha of the code> OUT=<folder> tools/device_check.sh [cuda:0]
#
# Run from the repository root after staging Warp (../shared/tools/stage_warp_for_device.sh).
# PERCH_WARP_COMMIT is required: the device's copy of the tree may carry a stale .git, and
# every reported figure must name the commit that ran. Each step has its own timeout
# (STEP_TIMEOUT, default 150 s) and log under $OUT; a failed step does not stop the rest.
set -uo pipefail
DEV=${1:-cuda:0}
OUT=${OUT:-device_check}
if [ -z "${PERCH_WARP_COMMIT:-}" ]; then
  echo "device_check: set PERCH_WARP_COMMIT to the commit of this tree (git rev-parse --short HEAD where it was made)" >&2
  exit 2
fi
export PERCH_WARP_COMMIT PERCH_WARP_SHARED=${PERCH_WARP_SHARED:-../shared}
mkdir -p "$OUT"
# The installed package maps perch_warp.kernels onto kernels/; a plain checkout needs a link,
# removed again at the end (a stray link changes how ruff sorts imports here).
if ! python3 -c "import perch_warp.kernels" 2>/dev/null; then
  ln -s ../kernels perch_warp/kernels && trap 'rm -f perch_warp/kernels' EXIT
fi

step() {
  local name=$1; shift
  local t0=$SECONDS
  timeout "${STEP_TIMEOUT:-150}" "$@" > "$OUT/$name.log" 2>&1
  local rc=$?
  echo "== $name: rc $rc, $((SECONDS - t0)) s"
  tail -n 4 "$OUT/$name.log"
}

step kernel_tests env PERCH_WARP_TEST_DEVICE="$DEV" python3 -m pytest -q -p no:cacheprovider \
  tests/test_render.py tests/test_raster.py tests/test_features.py tests/test_score.py tests/test_bound.py \
  tests/test_engine.py tests/test_refine.py
for s in exhaustive pruned coarse-to-fine; do
  step "bench_$s" python3 -m perch_warp bench --device "$DEV" --search "$s" --repeat 3 --no-peer --out "$OUT/bench_$s"
done
# The raster form of kernel #1 (auto picks it on the CPU only): is it faster on this GPU too?
# (Short settings: the whole script should stay within one 600 s device call.)
step bench_exhaustive_raster python3 -m perch_warp bench --device "$DEV" --search exhaustive --renderer raster \
  --repeat 1 --no-peer --out "$OUT/bench_exhaustive_raster"
step render_cost python3 tools/render_cost.py --device "$DEV" --poses 1000
# Kernel #2's conv1: the Warp kernel against torch's conv2d (cuDNN) on the same boxes (auto keeps warp on GPUs).
step conv_compare python3 tools/conv_compare.py --device "$DEV" --poses 1000 --out "$OUT/conv_compare.json"
step bvh_options python3 tools/bvh_options.py --device "$DEV" --poses 3000 --leaf-sizes 1 2 4 8
grep -h -E "^(commit|search|renderer|total|refine|candidates|throughput|refinement|pose found)" "$OUT"/bench_*/bench.txt 2>/dev/null
