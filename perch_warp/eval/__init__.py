"""`python -m perch_warp eval`: the thesis's evaluation protocol (§4.1) on a BOP dataset.

Targets: every ground-truth instance of a selected object in the selected images.
For each, the table frame comes from the image's `cam_R_w2c`/`cam_t_w2c` (else a
RANSAC plane fit to its depth image); the object's height, roll and pitch come from
the ground truth (`decompose_on_table`), and only (x, y, yaw) are searched over a
region that never depends on the ground truth (default: the visible table clipped
to 1 m x 1 m, `SearchSpace.visible_table`).

Outputs in OUTDIR:
  results.csv      BOP results (mm); the estimate for the k-th ground-truth instance of
                   an object in an image is the k-th row of that object in that image
                   (BOP rows have no instance index). `time` is the seconds spent on the
                   whole image (the sum over its targets), the same on all its rows, as
                   the BOP toolkit requires.
  targets.jsonl    one line per finished target: exact per-target time and search details; a target
                   that failed (bad ground truth, an error in its search) gets a line with "failed":
                   its reason, and the run goes on with the others (exit code 1 at the end).
  per_target.csv   errors of every target (ADD-S, ADD, translation mm, yaw deg, ...); failed targets
                   with their reason in `failure`.
  summary.json     metrics per object and over all objects, and per image label value
                   (`by_label`, see IMAGE_LABEL_KEYS); table.txt the printed table.
  adds_curve.png, occlusion.png (when scene_gt_info.json exists), lighting.png (when images
  carry a `lighting` label), errors.png, gallery.png.

Resuming: both results.csv and targets.jsonl are brought up to date after every
target (results.csv is rewritten atomically, so it is always a valid BOP file); a
rerun of the same command skips the targets found in either file, and tries failed ones
again. A journal line torn by a crash (no final newline) is cut off before appending. One
run at a time per OUTDIR: an flock on OUTDIR/.perch_warp.lock refuses a second, naming its pid.
"""
