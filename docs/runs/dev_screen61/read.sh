#!/bin/bash
# merge the four journals into one folder evaluated on DEV40, summarise, and read the rule
set -e
cd /work/pin61 && . /work/main/.venv/bin/activate
export PERCH_WARP_WEIGHTS=/work/shared/weights/bvlc_alexnet_conv1.npz PYTHONPATH=/work/pin61
M=/work/dev/s61/MERGED; rm -rf $M; mkdir -p $M
cp /work/main/docs/runs/dev_screen59/J_occ/eval_config.json $M/
python3 - <<'PY'
import json
c=json.load(open('/work/dev/s61/MERGED/eval_config.json')); c['dataset']='/work/dev/DEV40'
json.dump(c,open('/work/dev/s61/MERGED/eval_config.json','w'),indent=1)
PY
cat /work/main/docs/runs/dev_screen59/J_occ/targets.jsonl /work/main/docs/runs/dev_screen59/J_occ_b/targets.jsonl /work/main/docs/runs/dev_screen60/J_occ_c/targets.jsonl /work/main/docs/runs/dev_screen60/J_occ_d/targets.jsonl $(ls /work/dev/s61/J_occ_e/targets.jsonl 2>/dev/null) > $M/targets.jsonl
python3 -c "import json;k=[(r[\"scene_id\"],r[\"im_id\"],r[\"inst\"]) for r in map(json.loads,open(\"$M/targets.jsonl\"))];print(\"lines\",len(k),\"unique\",len(set(k)))"
python -m perch_warp eval --dataset /work/dev/DEV40 --objects 3 4 8 9 --out $M --weights caffe --device cpu --search coarse-to-fine --beam 128 --no-plots --cpu-threads 1 --joint --occluders answers > /work/dev/s61/log_merged 2>&1
python3 - <<'PY'
import csv, json
import numpy as np
from perch_warp.eval.metrics import mean_interval
from perch_warp import pose_error
rows=list(csv.DictReader(open('/work/dev/s61/MERGED/per_target.csv')))
e2=np.array([float(r['adds_mm'])/1000 for r in rows])
e1=np.array([float(r['first_adds_mm'])/1000 if r['first_adds_mm'] not in ('','nan') else float(r['adds_mm'])/1000 for r in rows])
s=lambda e: 100*np.maximum(0,1-e/0.1)
d=s(e2)-s(e1)
print('n',len(rows),'first AUC %.2f <2cm %d'%(s(e1).mean(),(e1<0.02).sum()),'second AUC %.2f <2cm %d'%(s(e2).mean(),(e2<0.02).sum()))
print('rule 1: gain %.3f CI95 [%.3f, %.3f]'%(d.mean(),*mean_interval(d)))
o=json.load(open('/work/dev/s61/MERGED/summary.json'))['occluders']
print('summary occluders n',o['n'],'auc_gain',o['auc_gain'],o['auc_gain_ci95'],'n_changed',o['n_changed'], 'cost', o.get('cost'))
PY
cd /work/main && python tools/accuracy_report.py $M --against docs/runs/dev_screen49/F_dir
