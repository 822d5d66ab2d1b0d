#!/usr/bin/env bash
# Stage issue 17's accuracy data for the GPU machine of the `device` tool, which reaches nothing
# outside the working tree it is sent: the seed-0 synthetic test set (its RGB images and BOP
# JSON; the table comes from cam_R_w2c, so depth and masks stay behind), the real YCB-Video
# frames with their JSON, the meshes these targets need, and the Caffe conv1 weights.
#
#   tools/stage_data_for_device.sh SYNTH_SET [SHARED]      (in the repository root)
#
# SYNTH_SET: the set made by `python -m perch_warp synth --models ../shared/data/ycbv/models
# --out SYNTH_SET --scenes 40 --seed 0 --objects 3 4 8 9 --lighting mixed --occlusion mixed`.
# SHARED: the shared data folder (default $PERCH_WARP_SHARED, else ../shared). Writes .devdata/
# (about 50 MB, laid out like SHARED so that PERCH_WARP_SHARED=.devdata finds the weights; added to
# .git/info/exclude); carry it in the `run` call of tools/device_accuracy.sh.
set -euo pipefail
synth=${1:?usage: tools/stage_data_for_device.sh SYNTH_SET [SHARED]}
shared=${2:-${PERCH_WARP_SHARED:-../shared}}
[ -f "$synth/test/000001/scene_gt.json" ] || { echo "stage_data_for_device: $synth is not a synthetic BOP set (no test/000001/scene_gt.json)" >&2; exit 2; }
[ -d "$shared/data/ycbv/models" ] || { echo "stage_data_for_device: no models under $shared/data/ycbv/models" >&2; exit 2; }
[ -f "$shared/weights/bvlc_alexnet_conv1.npz" ] || { echo "stage_data_for_device: no $shared/weights/bvlc_alexnet_conv1.npz" >&2; exit 2; }
tmp=$(mktemp -d .devdata.XXXXXX)
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/synth_ycbv/test/000001" "$tmp/data/ycbv/test" "$tmp/data/ycbv/models" "$tmp/weights"
cp -r "$synth/test/000001/rgb" "$synth/test/000001/"*.json "$tmp/synth_ycbv/test/000001/"
for f in "$synth"/*.json; do
  [ "$(basename "$f")" = dataset_info.json ] || cp "$f" "$tmp/synth_ycbv/"
done
for s in "$shared"/data/ycbv/test/*/; do
  mkdir -p "$tmp/data/ycbv/test/$(basename "$s")"
  cp -r "$s"rgb "$s"*.json "$tmp/data/ycbv/test/$(basename "$s")/"
done
# The targets with a mesh: synthetic objects 3 4 8 9; in the real frames 1 3 4 5 6 8 9.
for o in 1 3 4 5 6 8 9; do cp "$shared"/data/ycbv/models/obj_$(printf %06d "$o").* "$tmp/data/ycbv/models/"; done
cp "$shared"/data/ycbv/models/models_info.json "$tmp/data/ycbv/models/" 2>/dev/null || true
cp "$shared/weights/bvlc_alexnet_conv1.npz" "$tmp/weights/"
rm -rf .devdata && mv "$tmp" .devdata && trap - EXIT
grep -qxF /.devdata/ .git/info/exclude 2>/dev/null || echo /.devdata/ >> .git/info/exclude
du -sh .devdata
