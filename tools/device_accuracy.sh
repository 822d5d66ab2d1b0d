#!/usr/bin/env bash
# Issue 17's test runs with the frozen configuration on a GPU, prepared to fit one `run` call of
# the `device` tool: the seed-0 synthetic set (88 targets) and the five real frames (11 targets
# with a mesh), each an `eval` with everything at its default but the device.
#
#   PERCH_WARP_COMMIT=<sha> OUT=<folder> [BUDGET_S=480] [SEARCH=auto] [RESUME=file.tgz] \
#       tools/device_accuracy.sh synth|real [cuda:0]
#
# Run from the repository root after staging Warp (../shared/tools/stage_warp_for_device.sh) and the
# data (tools/stage_data_for_device.sh, carry .devdata). `eval` journals each target as it finishes,
# so the run stops after BUDGET_S seconds with its finished targets kept: OUT/<set>.tgz holds the
# output folder (heat maps included, one file, since the device returns at most 8), and a later
# call carrying that file as RESUME goes on from there. SEARCH=coarse-to-fine (beam 512) is the
# faster choice if the default search does not fit the device time. Report figures with
# `python tools/accuracy_report.py` on the unpacked folder, naming PERCH_WARP_COMMIT and the device.
set -uo pipefail
SET=${1:?usage: tools/device_accuracy.sh synth|real [cuda:0]}
DEV=${2:-cuda:0}
OUT=${OUT:-device_accuracy}
if [ -z "${PERCH_WARP_COMMIT:-}" ]; then
  echo "device_accuracy: set PERCH_WARP_COMMIT to the commit of this tree (git rev-parse --short HEAD where it was made)" >&2
  exit 2
fi
[ -d .devdata/weights ] || { echo "device_accuracy: no .devdata/ here: run tools/stage_data_for_device.sh and carry .devdata" >&2; exit 2; }
case $SET in
  synth) args=(--dataset .devdata/synth_ycbv --objects 3 4 8 9) ;;
  real) args=(--dataset .devdata/data/ycbv --scenes 1 2 48 51 52) ;;
  *) echo "device_accuracy: the set must be synth or real, got '$SET'" >&2; exit 2 ;;
esac
export PERCH_WARP_COMMIT PERCH_WARP_SHARED=$PWD/.devdata PYTHONUNBUFFERED=1
mkdir -p "$OUT"
if ! python3 -c "import perch_warp.kernels" 2>/dev/null; then
  ln -s ../kernels perch_warp/kernels && trap 'rm -f perch_warp/kernels' EXIT
fi
work=$(mktemp -d)
if [ -n "${RESUME:-}" ]; then
  tar -xzf "$RESUME" -C "$work" || { echo "device_accuracy: cannot unpack RESUME=$RESUME" >&2; exit 2; }
fi
t0=$SECONDS
timeout "${BUDGET_S:-480}" python3 -m perch_warp eval "${args[@]}" --models .devdata/data/ycbv/models \
  --out "$work/$SET" --weights caffe --device "$DEV" --search "${SEARCH:-auto}" --no-plots 2>&1 | tee "$OUT/$SET.log"
rc=${PIPESTATUS[0]}
case $rc in 0) how=done ;; 124) how="budget reached, resumable" ;; *) how=failed ;; esac
echo "== eval $SET on $DEV at $PERCH_WARP_COMMIT: rc $rc ($how), $((SECONDS - t0)) s, $( (wc -l < "$work/$SET/targets.jsonl") 2>/dev/null || echo 0) targets journalled"
tar -czf "$OUT/$SET.tgz" -C "$work" "$SET"
