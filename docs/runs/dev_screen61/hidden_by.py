"""Who hides the development set's low-visibility targets: for each target (objects 3, 4, 8, 9) less
than half visible, its hidden pixels (its ground-truth mask minus its visible mask) split by the
instance whose visible mask covers them — another target, or an object that is not a target.
Ground truth only (analysis, never a search input).

Usage: python hidden_by.py DATASET/test/000001
"""

import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

TARGETS = {3, 4, 8, 9}


def main(scene: Path) -> None:
    gt = json.loads((scene / "scene_gt.json").read_text())
    info = json.loads((scene / "scene_gt_info.json").read_text())
    totals = np.zeros(3)
    by_other = 0
    for im, objs in gt.items():
        im = int(im)
        visible = [np.asarray(Image.open(scene / f"mask_visib/{im:06d}_{k:06d}.png")) > 0 for k in range(len(objs))]
        for k, o in enumerate(objs):
            fract = info[str(im)][k]["visib_fract"]
            if o["obj_id"] not in TARGETS or fract >= 0.5:
                continue
            hidden = (np.asarray(Image.open(scene / f"mask/{im:06d}_{k:06d}.png")) > 0) & ~visible[k]
            others = [j for j in range(len(objs)) if j != k]
            by_t = sum(int((hidden & visible[j]).sum()) for j in others if objs[j]["obj_id"] in TARGETS)
            by_n = sum(int((hidden & visible[j]).sum()) for j in others if objs[j]["obj_id"] not in TARGETS)
            totals += (hidden.sum(), by_t, by_n)
            by_other += by_n > by_t
            print(
                f"1/{im}/{k} obj {o['obj_id']} visible {fract:.2f}: hidden px {hidden.sum()}, "
                f"by targets {by_t}, by non-targets {by_n}"
            )
    print(
        f"hidden pixels by targets {totals[1] / totals[0]:.2f}, by non-targets {totals[2] / totals[0]:.2f}; "
        f"targets hidden mainly by non-targets: {by_other}"
    )


if __name__ == "__main__":
    main(Path(sys.argv[1]))
