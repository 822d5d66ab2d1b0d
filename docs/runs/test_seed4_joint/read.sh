#!/bin/bash
# The seed-4 test set's reading, written at stop 62 before any of its lines was read: merge the four
# journals (S4, S4b, S4c, S4d; 93 unique targets) into one folder evaluated on SEED4 (no search runs:
# every target is journalled), summarise, and print the report. Usage: read.sh PINNED_CLONE
set -e
PIN=${1:?pinned clone}
cd "$PIN" && . /work/main/.venv/bin/activate
export PERCH_WARP_WEIGHTS=/work/shared/weights/bvlc_alexnet_conv1.npz PYTHONPATH=$PIN
R=/work/main/docs/runs/test_seed4_joint
M=/work/dev/s62/MERGED; rm -rf $M; mkdir -p $M
cp $R/S4/eval_config.json $M/
cat $R/S4/targets.jsonl $R/S4b/targets.jsonl $R/S4c/targets.jsonl $R/S4d/targets.jsonl > $M/targets.jsonl
python3 -c "import json;k=[(r['scene_id'],r['im_id'],r['inst']) for r in map(json.loads,open('$M/targets.jsonl'))];print('lines',len(k),'unique',len(set(k)));assert len(k)==len(set(k))==93"
python -m perch_warp eval --dataset /work/dev/SEED4 --objects 3 4 8 9 --out $M --weights caffe --device cpu \
    --search coarse-to-fine --beam 128 --no-plots --cpu-threads 1 --joint > /work/dev/s62/log_merged 2>&1
tail -n 30 /work/dev/s62/log_merged
python /work/main/tools/accuracy_report.py $M --json /work/dev/s62/report.json
