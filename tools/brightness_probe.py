"""How bright is each target in the photo against its render? (issue 17 (c), the exposure term)

    python tools/brightness_probe.py --dataset DEV [--models DIR] [--objects 3 4 8 9] [--max-images 16]
        [--csv OUT.csv]

For every ground-truth instance: the object rendered at its ground-truth pose (the texture's albedo, as
the search renders it), and on the pixels that both the render and the instance's visible mask
(mask_visib/; with --whole-render, where it is absent, the render alone) cover, the photo's mean R, G,
B over the render's. Far from 1, the render and the photo disagree in brightness before any texture
is compared. `clipped`: the share of those pixels that the photo holds at white (255) in some channel,
where a camera burnt the texture out (the tone term's premise). Prints one line per target with its
lighting label, and the spread over all targets. A diagnostic that reads the ground truth: never a
search setting. Exit 1 on bad input.
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from perch_warp import bop
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.features import load_feature_weights
from perch_warp.image import load_rgb
from perch_warp.mesh import load_mesh
from perch_warp.outputs import atomic_write_text

MIN_PIXELS = 50  # fewer visible rendered pixels than this: no ratio


def ratios(args: argparse.Namespace) -> list[dict]:
    ds = bop.open_dataset(args.dataset, "test", args.models)
    sel = bop.select_targets(ds, args.scenes, args.objects, args.max_images)
    weights = load_feature_weights(args.weights)
    engines: dict[int, Engine] = {}
    rows = []
    for im in sel.images:
        image = load_rgb(im.rgb).astype(np.float64) / 255.0
        for t in im.targets:
            if t.problem is not None:
                continue
            if t.obj_id not in engines:
                mesh = load_mesh(sel.model_paths[t.obj_id])
                engines[t.obj_id] = Engine(mesh, weights, "cpu", EngineConfig())
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = t.R_gt, t.t_gt_m
            rgb, mask = engines[t.obj_id].render(im.camera, T)
            visib = im.rgb.parent.parent / "mask_visib" / f"{im.im_id:06d}_{t.inst:06d}.png"
            if visib.is_file():
                both = mask & (np.asarray(Image.open(visib)) > 0)
            elif args.whole_render:
                both = mask
            else:
                raise PerchError(
                    f"{visib}: no visible mask for target {t.key} (BOP mask_visib/); --whole-render compares "
                    "the whole rendered silhouette instead (occluders then count)"
                )
            if both.sum() < MIN_PIXELS:
                continue
            ratio = image[both].mean(0) / np.maximum(rgb[both].astype(np.float64).mean(0), 1e-3)
            clipped = float((image[both] >= 1.0).any(axis=1).mean())
            rows.append(
                {
                    "scene_id": t.scene_id,
                    "im_id": t.im_id,
                    "inst": t.inst,
                    "obj_id": t.obj_id,
                    "lighting": t.labels.get("lighting", ""),
                    "visib_fract": t.visib_fract,
                    "ratio_r": ratio[0],
                    "ratio_g": ratio[1],
                    "ratio_b": ratio[2],
                    "ratio": float(ratio.mean()),
                    "clipped": clipped,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", required=True, help="BOP dataset folder (test/SCENE/rgb, mask_visib)")
    ap.add_argument("--models", default=None, help="mesh folder (default: the dataset's models/)")
    ap.add_argument("--scenes", type=int, nargs="*", default=None)
    ap.add_argument("--objects", type=int, nargs="*", default=None)
    ap.add_argument("--max-images", type=int, default=None)
    ap.add_argument("--weights", default="caffe")
    ap.add_argument(
        "--whole-render",
        action="store_true",
        help="where a target has no mask_visib/ file, compare the whole rendered silhouette (occluders count)",
    )
    ap.add_argument("--csv", type=Path, default=None, help="write the per-target ratios here")
    args = ap.parse_args(argv)
    try:
        rows = ratios(args)
    except PerchError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for r in rows:
        print(
            f"{r['scene_id']}/{r['im_id']}/{r['inst']} obj {r['obj_id']:2d} {r['lighting']:6s} "
            f"visible {r['visib_fract'] if r['visib_fract'] is not None else float('nan'):.2f}  photo/render "
            f"R {r['ratio_r']:.2f} G {r['ratio_g']:.2f} B {r['ratio_b']:.2f}  clipped {r['clipped']:.0%}"
        )
    if rows:
        m = np.array([r["ratio"] for r in rows])
        print(
            f"{len(m)} targets: photo/render brightness min {m.min():.2f}, median {np.median(m):.2f}, "
            f"max {m.max():.2f}; outside [0.71, 1.41] (half a stop): {np.mean((m < 2**-0.5) | (m > 2**0.5)):.0%}"
        )
        for label in sorted({r["lighting"] for r in rows}):
            c = np.array([r["clipped"] for r in rows if r["lighting"] == label])
            print(
                f"  {label or 'unlabelled'}: {len(c)} targets, share of visible pixels clipped at white: "
                f"median {np.median(c):.0%}, max {c.max():.0%}, above 10 % for {int((c > 0.1).sum())}"
            )
    if args.csv is not None and rows:
        buf = io.StringIO(newline="")
        w = csv.DictWriter(buf, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
        atomic_write_text(args.csv, buf.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
