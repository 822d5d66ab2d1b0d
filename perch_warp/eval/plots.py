"""The evaluation's PNG plots (matplotlib): ADD-S curves, occlusion, lighting, errors and the gallery."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from .. import pose_error
from ..bop import Selection, TableCache
from ..camera import Camera
from ..image import load_rgb
from .metrics import ADDS_THRESHOLD_M, AUC_MAX_THRESHOLD_M, GeometryCache

# Each target's heat map (perch_warp.score_map.ScoreMap as .npz), written by the eval loop.
HEATMAP_DIR = "heatmaps"


def heatmap_path(out_dir: Path, key: tuple[int, int, int]) -> Path:
    """Where target (scene_id, im_id, inst)'s heat map lies under OUTDIR."""
    scene, im, inst = key
    return Path(out_dir) / HEATMAP_DIR / f"{scene:06d}_{im:06d}_{inst}.npz"


def silhouette(camera: Camera, vertices_m: np.ndarray, faces: np.ndarray, R: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    """Bool (H, W) mask of the model's projection (every face filled; occlusion by other objects ignored)."""

    pc = vertices_m @ np.asarray(R).T + np.asarray(t_m).reshape(3)
    img = Image.new("1", (camera.width, camera.height), 0)
    tri_z = pc[faces][:, :, 2]
    ok = np.all(tri_z > 1e-3, axis=1)
    if not ok.any():
        return np.zeros((camera.height, camera.width), dtype=bool)
    uv = camera.project(pc)
    tris = uv[faces[ok]]
    # Faces far outside the image only slow PIL down.
    lim = 4 * max(camera.width, camera.height)
    tris = tris[np.all(np.abs(tris) < lim, axis=(1, 2))]
    draw = ImageDraw.Draw(img)
    for tri in tris.tolist():
        draw.polygon([tuple(p) for p in tri], fill=1)
    return np.asarray(img, dtype=bool)


def _crop_box(masks: list[np.ndarray], shape: tuple[int, int], margin: float = 0.35, min_size: int = 80):
    h, w = shape
    ys, xs = [], []
    for m in masks:
        yy, xx = np.nonzero(m)
        ys += [yy.min(), yy.max()] if yy.size else []
        xs += [xx.min(), xx.max()] if xx.size else []
    if not xs:
        return 0, h, 0, w
    cx, cy = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
    half = max(max(xs) - min(xs), max(ys) - min(ys), min_size) * (0.5 + margin)
    x0, x1 = int(max(0, cx - half)), int(min(w, cx + half + 1))
    y0, y1 = int(max(0, cy - half)), int(min(h, cy + half + 1))
    return y0, y1, x0, x1


def make_plots(
    out_dir: Path,
    rows: list[dict],
    summary: dict,
    selection: Selection,
    tables: TableCache,
    geometry: GeometryCache,
    gallery: int = 4,
) -> list[str]:
    """adds_curve.png (thesis Fig. 4.2), occlusion.png (Fig. 4.6), lighting.png, errors.png, gallery.png.

    Returns the names of the files written.
    """
    import matplotlib  # imported here: about 0.3 s, and only runs with plots pay it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    by_obj: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_obj[r["obj_id"]].append(r)
    names = {int(k): v["name"] for k, v in summary["objects"].items()}

    _adds_curve(out_dir / "adds_curve.png", rows, by_obj, names, plt)
    made.append("adds_curve.png")
    occ = summary.get("occlusion")
    if occ is not None:
        _occlusion_plot(out_dir / "occlusion.png", occ, names, plt)
        made.append("occlusion.png")

    lighting = (summary.get("by_label") or {}).get("lighting")
    if lighting:
        _lighting_plot(out_dir / "lighting.png", lighting, plt)
        made.append("lighting.png")

    _errors_plot(out_dir / "errors.png", by_obj, names, plt)
    made.append("errors.png")

    if gallery > 0:
        made.append(_gallery(out_dir / "gallery.png", rows, names, selection, geometry, gallery, plt))
        worst = _worst_heatmaps(out_dir, rows, names, selection, tables, gallery, plt)
        if worst:
            made.append(worst)
    return made


def _worst_heatmaps(out_dir: Path, rows: list[dict], names: dict, selection: Selection, tables: TableCache,
                    k: int, plt) -> str | None:  # fmt: skip
    """worst_heatmaps.png: the heat maps (perch_warp.heatmap) of the k targets of largest ADD-S that have
    one saved (searched by this engine, in this OUTDIR), the ground truth marked; None when there is none."""
    from ..heatmap import draw_panels
    from ..score_map import ScoreMap

    order = sorted(range(len(rows)), key=lambda i: (-rows[i]["adds_mm"], i))
    key = [(rows[i]["scene_id"], rows[i]["im_id"], rows[i]["inst"]) for i in order]
    picked = [(i, heatmap_path(out_dir, kk)) for i, kk in zip(order, key, strict=True)]
    picked = [(i, p) for i, p in picked if p.exists()][:k]
    if not picked:
        return None
    images = {(im.scene_id, im.im_id): im for im in selection.images}
    fig, axes = plt.subplots(len(picked), 2, figsize=(11, 4.0 * len(picked)), squeeze=False)
    for (a, b), (i, p) in zip(axes, picked, strict=True):
        r = rows[i]
        im = images[(r["scene_id"], r["im_id"])]
        smap = ScoreMap.load(p)
        answer = (r["x_est_m"], r["y_est_m"])
        mesh = draw_panels(
            a, b, load_rgb(im.rgb), im.camera, tables.get(im)[0], smap, answer, (r["x_gt_m"], r["y_gt_m"])
        )
        fig.colorbar(mesh, ax=b, label="best score over yaw", fraction=0.046, pad=0.03)
        conf = r.get("confidence")
        a.set_title(
            f"{names[r['obj_id']]}: scene {r['scene_id']} im {r['im_id']} inst {r['inst']}, "
            f"ADD-S {r['adds_mm']:.1f} mm, confidence {'-' if conf is None else format(conf, '.4f')}",
            fontsize=8,
        )
        b.set_title("star: answer, x: truth, numbers: peaks; faded: the best seen (a lower bound); grey: "
                    + (smap.why_unknown or "none"), fontsize=7)  # fmt: skip
    fig.tight_layout()
    fig.savefig(out_dir / "worst_heatmaps.png", dpi=80)
    plt.close(fig)
    return "worst_heatmaps.png"


def _adds_curve(path: Path, rows: list[dict], by_obj: dict[int, list[dict]], names: dict, plt) -> None:
    """ADD-S threshold curves, one panel per object (+ all targets): thesis Fig. 4.2."""
    # ADD-S threshold curves, one panel per object (+ all targets).
    panels = [(names[o], by_obj[o]) for o in sorted(by_obj)]
    if len(panels) > 1:
        panels.append(("all objects (pooled)", rows))
    ncols = min(4, len(panels))
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols, 3.2 * nrows), squeeze=False)
    thr = np.linspace(0.0, AUC_MAX_THRESHOLD_M, 401)
    for ax, (name, rs) in zip(axes.ravel(), panels, strict=False):
        e = np.array([r["adds_mm"] for r in rs]) / 1000.0
        ax.plot(
            thr * 100,
            100 * pose_error.accuracy_curve(e, thr),
            color="C0",
            lw=2,
            label=f"AUC {pose_error.auc(e):.2f}\n<2cm {pose_error.accuracy_below(e):.1f}%",
        )
        ax.axvline(ADDS_THRESHOLD_M * 100, color="0.6", ls="--", lw=1)
        ax.set(
            xlim=(0, AUC_MAX_THRESHOLD_M * 100),
            ylim=(0, 101),
            xlabel="ADD-S threshold (cm)",
            ylabel="accuracy (%)",
            title=f"{name} (n={len(rs)})",
        )
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
    for ax in axes.ravel()[len(panels) :]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _occlusion_plot(path: Path, occ: dict, names: dict, plt) -> None:
    """ADD-S < 2 cm accuracy in occlusion bins, all objects as bars and each object as a line: Fig. 4.6."""
    edges = np.array(occ["bin_edges_occlusion"])
    centres = 100 * (edges[:-1] + edges[1:]) / 2
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    acc_all = [np.nan if a is None else a for a in occ["all"]["accuracy_pct"]]
    bars = ax.bar(centres, acc_all, width=8, color="0.8", label="all objects")
    for b, n in zip(bars, occ["all"]["n"], strict=True):
        if n:
            ax.annotate(
                f"n={n}",
                (b.get_x() + b.get_width() / 2, b.get_height()),
                ha="center",
                va="bottom",
                fontsize=7,
                xytext=(0, 2),
                textcoords="offset points",
            )
    for k, (obj, o) in enumerate(occ["objects"].items()):
        a = np.array([np.nan if v is None else v for v in o["accuracy_pct"]])
        ax.plot(centres, a, "o-", color=f"C{k}", label=names[int(obj)], ms=4)
    ax.set(
        xlim=(0, 100),
        ylim=(0, 110),
        xlabel="occlusion = 1 - visib_fract (%)",
        ylabel="ADD-S < 2 cm (%)",
        title="accuracy against occlusion",
        xticks=100 * edges,
    )
    ax.legend(fontsize=8, loc="lower left")
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _errors_plot(path: Path, by_obj: dict[int, list[dict]], names: dict, plt) -> None:
    """Translation vs yaw error, to tell position misses from orientation misses."""
    # Translation vs yaw error, to tell position misses from orientation misses.
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for k, obj in enumerate(sorted(by_obj)):
        rs = by_obj[obj]
        ax.scatter(
            [max(r["te_mm"], 0.1) for r in rs],
            [r["yaw_err_deg"] for r in rs],
            s=14,
            color=f"C{k}",
            label=names[obj],
            alpha=0.8,
        )
    ax.axvline(ADDS_THRESHOLD_M * 1000, color="0.6", ls="--", lw=1)
    ax.set(
        xscale="log",
        xlabel="translation error (mm, log)",
        ylabel="yaw error (deg)",
        ylim=(-5, 185),
        title="errors per target (yaw ignores symmetries)",
    )
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _lighting_plot(path: Path, by_value: dict[str, dict], plt) -> None:
    """ADD-S < 2 cm accuracy and AUC per lighting label value, side by side, with the target count over each pair."""
    values = list(by_value)
    x = np.arange(len(values))
    width = 0.38
    fig, ax = plt.subplots(figsize=(max(4.5, 1.6 * len(values) + 2.0), 4.0))
    for offset, metric, label, colour in (
        (-width / 2, "adds_below_2cm_pct", "ADD-S < 2 cm (%)", "C0"),
        (width / 2, "auc", "AUC (0-10 cm)", "C1"),
    ):
        heights = [np.nan if by_value[v][metric] is None else by_value[v][metric] for v in values]
        ax.bar(x + offset, heights, width=width, color=colour, label=label)
    for i, v in enumerate(values):
        top = max((m for m in (by_value[v]["adds_below_2cm_pct"], by_value[v]["auc"]) if m is not None), default=0.0)
        ax.annotate(
            f"n={by_value[v]['n']}",
            (x[i], top),
            ha="center",
            va="bottom",
            fontsize=8,
            xytext=(0, 3),
            textcoords="offset points",
        )
    ax.set(
        xticks=x,
        xticklabels=values,
        yticks=np.arange(0, 101, 20),
        ylim=(0, 130),  # room above 100 % for the counts and the legend
        xlabel="lighting (scene_camera.json label)",
        ylabel="%",
        title="accuracy against lighting",
    )
    ax.legend(fontsize=8, loc="upper center", ncol=2)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _gallery(
    path: Path, rows: list[dict], names: dict, selection: Selection, geometry: GeometryCache, k: int, plt
) -> str:
    """Best and worst targets by ADD-S: crops with the ground truth (green) and the estimate (magenta)."""
    from matplotlib.patches import Patch

    order = sorted(range(len(rows)), key=lambda i: (rows[i]["adds_mm"], i))
    # With fewer than 2k targets, the better half are "best" and the rest "worst".
    n_best = min(k, math.ceil(len(order) / 2))
    best = order[:n_best]
    worst = order[n_best:][::-1][:k]
    sections = [("best", best)] + ([("worst", worst)] if worst else [])
    images = {(im.scene_id, im.im_id): im for im in selection.images}
    ncols = max(len(s[1]) for s in sections)
    fig, axes = plt.subplots(len(sections), ncols, figsize=(3.0 * ncols, 3.4 * len(sections)), squeeze=False)
    for row_axes, (label, idxs) in zip(axes, sections, strict=True):
        for ax in row_axes:
            ax.axis("off")
        for ax, i in zip(row_axes, idxs, strict=False):
            r = rows[i]
            im = images[(r["scene_id"], r["im_id"])]
            rgb = load_rgb(im.rgb)
            V, F, _ = geometry.get(r["obj_id"])
            m_gt = silhouette(im.camera, V, F, r["R_gt"], r["t_gt_m"])
            m_est = silhouette(im.camera, V, F, r["R_est"], r["t_est_m"])
            y0, y1, x0, x1 = _crop_box([m_gt, m_est], rgb.shape[:2])
            ax.imshow(rgb[y0:y1, x0:x1])
            for m, colour in ((m_gt, (0.0, 0.9, 0.0)), (m_est, (1.0, 0.0, 1.0))):
                c = m[y0:y1, x0:x1]
                if c.any():
                    tint = np.zeros(c.shape + (4,))
                    tint[c] = (*colour, 0.22)
                    ax.imshow(tint)
                    ax.contour(c.astype(float), levels=[0.5], colors=[colour], linewidths=1.4)
            ax.set_title(
                f"{label}: {names[r['obj_id']]}\nscene {r['scene_id']} im {r['im_id']} inst {r['inst']}\n"
                f"ADD-S {r['adds_mm']:.1f} mm, yaw err {r['yaw_err_deg']:.0f} deg",
                fontsize=7,
            )
    fig.legend(
        handles=[Patch(color=(0, 0.9, 0), label="ground truth"), Patch(color=(1, 0, 1), label="estimate")],
        loc="lower center",
        ncol=2,
        fontsize=8,
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name
