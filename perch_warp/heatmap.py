"""`--heatmap PNG`: the best score over yaw at each (x, y) cell of the searched table (perch_warp.score_map),
drawn (a) over the photo through the table plane and (b) as a top-down table map, with the best
distinct peaks numbered and the answer starred.

Cells whose best is not known (the pruned search left a candidate unscored, whose bound says only
that it is below the top-k; coarse-to-fine visited some of its poses or none) are never coloured as if
known: where some pose of the cell was scored, its best such score (`ScoreMap.seen`, a lower bound of
the cell's best) is drawn in the same colours faded towards grey, so a coarse-to-fine search's map
shows where it looked and what it found there; cells where no pose was scored are grey; cells where no
candidate shows a feature point are left blank. Peaks are ranked over both, known and seen: each is a
pose that was scored.
"""

from __future__ import annotations

import io
import math
import textwrap
from pathlib import Path

import numpy as np

from .camera import Camera
from .outputs import atomic_write
from .peaks import SEPARATION_STEPS
from .score_map import ScoreMap
from .table import Table

UNKNOWN_GREY = (0.55, 0.55, 0.55)
OVERLAY_ALPHA = 0.55  # of a cell's colour over the photo
N_PEAKS = 5
SEEN_FADE = 0.5  # a seen-only cell's colour mixed this much with UNKNOWN_GREY


def shown_scores(smap: ScoreMap) -> tuple[np.ndarray, np.ndarray]:
    """(values, seen_only), both (nx, ny): the cell's best where known (finite or -inf), else the best
    score seen there (a lower bound of its best) where some pose was scored, else NaN; and where the
    value is such a lower bound."""
    values = smap.best.copy()
    seen_only = np.zeros(values.shape, dtype=bool)
    if smap.seen is not None:
        seen_only = np.isnan(values) & np.isfinite(smap.seen)
        values[seen_only] = smap.seen[seen_only]
    return values, seen_only


def _norm(values: np.ndarray):
    from matplotlib.colors import Normalize

    known = values[np.isfinite(values)]
    lo, hi = (float(known.min()), float(known.max())) if known.size else (0.0, 1.0)
    return Normalize(lo, hi if hi > lo else lo + 1e-9)


def _faded(rgba: np.ndarray) -> np.ndarray:
    """Colours (..., 4) mixed SEEN_FADE with grey: a lower bound, drawn apart from a known best."""
    out = np.array(rgba, dtype=float)
    out[..., :3] = (1 - SEEN_FADE) * out[..., :3] + SEEN_FADE * np.asarray(UNKNOWN_GREY)
    return out


def _peaks(smap: ScoreMap, values: np.ndarray) -> list[tuple[float, float, float, float]]:
    """Up to N_PEAKS distinct peaks (x_m, y_m, yaw_rad, score) over the shown values, best first."""
    yaw = smap.best_yaw_rad if smap.seen_yaw_rad is None else np.where(
        np.isfinite(smap.best), smap.best_yaw_rad, smap.seen_yaw_rad
    )  # fmt: skip
    view = ScoreMap(smap.xs_m, smap.ys_m, smap.step_m, np.where(np.isfinite(values), values, np.nan),
                    smap.upper, yaw, smap.why_unknown)  # fmt: skip
    return view.peaks(N_PEAKS, SEPARATION_STEPS)


def cell_quads(smap: ScoreMap, camera: Camera, table: Table) -> tuple[np.ndarray, np.ndarray]:
    """Pixel corners (nx, ny, 4, 2) of each cell's square on the table top (z = 0, table frame), and
    whether all four corners lie in front of the camera (nx, ny)."""
    h = smap.step_m / 2
    X, Y = np.meshgrid(smap.xs_m, smap.ys_m, indexing="ij")
    dx, dy = np.array([-h, h, h, -h]), np.array([-h, -h, h, h])
    corners = np.stack([X[..., None] + dx, Y[..., None] + dy, np.zeros(X.shape + (4,))], -1)
    pc = table.to_camera(corners)
    front = (pc[..., 2] > 1e-3).all(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return camera.project(pc), front


def photo_layer(image_rgb: np.ndarray, camera: Camera, table: Table, smap: ScoreMap, cmap, norm) -> np.ndarray:
    """The photo (uint8 H x W x 3) with each cell's colour blended in: known, seen only (faded) or grey."""
    from PIL import Image, ImageDraw

    uv, front = cell_quads(smap, camera, table)
    layer = Image.new("RGBA", (camera.width, camera.height), (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    a = int(255 * OVERLAY_ALPHA)
    lim = 4 * max(camera.width, camera.height)  # far-off quads only slow PIL down
    values, seen_only = shown_scores(smap)
    for i, j in zip(*np.nonzero(front & ~np.isneginf(values)), strict=True):
        q = uv[i, j]
        if not np.all(np.abs(q) < lim):
            continue
        v = values[i, j]
        if np.isnan(v):
            rgb = UNKNOWN_GREY
        else:
            rgb = (_faded(cmap(norm(v))) if seen_only[i, j] else np.asarray(cmap(norm(v))))[:3]
        draw.polygon([tuple(p) for p in q.tolist()], fill=(*(int(255 * c) for c in rgb), a))
    base = Image.fromarray(np.asarray(image_rgb, dtype=np.uint8)).convert("RGBA")
    return np.asarray(Image.alpha_composite(base, layer).convert("RGB"))


def draw_panels(ax_photo, ax_map, image_rgb, camera: Camera, table: Table, smap: ScoreMap, answer, truth=None):
    """Draw the two panels on matplotlib axes; answer and truth: (x_m, y_m, ...) table frame or None.
    Returns the map's image (for a colour bar)."""
    import matplotlib as mpl

    values, seen_only = shown_scores(smap)
    cmap, norm = mpl.colormaps["viridis"], _norm(values)
    peaks = _peaks(smap, values)
    ax_photo.imshow(photo_layer(image_rgb, camera, table, smap, cmap, norm))
    marks = [(p[0], p[1], str(n + 1)) for n, p in enumerate(peaks)]
    uv = camera.project(table.to_camera(np.array([[m[0], m[1], 0.0] for m in marks] + [[*answer[:2], 0.0]])))
    for (u, v), (_, _, label) in zip(uv[:-1], marks, strict=True):
        _mark_peak(ax_photo, u, v, label)
    ax_photo.plot(*uv[-1], marker="*", color="magenta", ms=12, mec="k")
    ax_photo.set_axis_off()
    s, xs, ys = smap.step_m, smap.xs_m, smap.ys_m
    extent = (xs[0] - s / 2, xs[-1] + s / 2, ys[0] - s / 2, ys[-1] + s / 2)
    known = np.where(np.isfinite(smap.best), smap.best, np.nan).T
    im = ax_map.imshow(known, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
    rgba = _faded(cmap(norm(np.where(seen_only, values, 0.0))))
    rgba[..., 3] = seen_only
    ax_map.imshow(np.swapaxes(rgba, 0, 1), origin="lower", extent=extent, interpolation="nearest")
    grey = mpl.colors.ListedColormap([UNKNOWN_GREY])
    ax_map.imshow(np.where(np.isnan(values), 0.0, np.nan).T, origin="lower", extent=extent, cmap=grey,
                  interpolation="nearest")  # fmt: skip
    for x, y, label in marks:
        _mark_peak(ax_map, x, y, label)
    ax_map.plot(answer[0], answer[1], marker="*", color="magenta", ms=12, mec="k", ls="", label="answer")
    if truth is not None:
        ax_map.plot(truth[0], truth[1], marker="x", color="lime", ms=9, mew=2, ls="", label="ground truth")
    ax_map.set(xlabel="x (m, table frame)", ylabel="y (m)", facecolor="white")
    return im


def _mark_peak(ax, u: float, v: float, label: str) -> None:
    """A dot at the peak and its rank beside it (up and right, so that the answer's star leaves it legible)."""
    from matplotlib import patheffects

    ax.plot(u, v, marker="o", ms=3, color="w", mec="k", mew=0.5)
    ax.annotate(label, (u, v), xytext=(4, 4), textcoords="offset points", color="w", fontsize=8, weight="bold",
                path_effects=[patheffects.withStroke(linewidth=2, foreground="k")])  # fmt: skip


def _legend(ax_map, smap: ScoreMap, has_truth: bool) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Line2D([], [], marker="*", color="magenta", mec="k", ms=10, ls="", label="answer"),
        Line2D([], [], marker="o", color="w", mec="k", ls="", label="1, 2, …: peaks, best first (distinct places)"),
    ]
    if has_truth:
        handles.append(Line2D([], [], marker="x", color="lime", mew=2, ls="", label="ground truth"))
    values, seen_only = shown_scores(smap)
    if seen_only.any():
        label = textwrap.fill(f"faded ({int(seen_only.sum())} cells): best not known, the best score seen there "
                              "drawn (a lower bound)", 40)  # fmt: skip
        import matplotlib as mpl

        handles.append(Patch(color=tuple(_faded(np.asarray(mpl.colormaps["viridis"](0.75)))[:3]), label=label))
    n_grey = int(np.isnan(values).sum())
    if n_grey:
        why = textwrap.fill(f"unknown, no pose scored ({n_grey} cells): {smap.why_unknown}", 40)
        handles.append(Patch(color=UNKNOWN_GREY, label=why))
    if np.isneginf(values).any():
        handles.append(Patch(facecolor="white", edgecolor="0.5", label="no pose shows a feature point"))
    ax_map.legend(handles=handles, fontsize=7, loc="upper left", bbox_to_anchor=(1.28, 1.0), frameon=False)


def render_heatmap(image_rgb, camera: Camera, table: Table, smap: ScoreMap, answer, title: str, truth=None) -> bytes:
    """Both panels side by side as PNG bytes; answer (x_m, y_m, yaw_rad), truth (x_m, y_m) or None."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [1.25, 1]})
    im = draw_panels(a, b, image_rgb, camera, table, smap, answer, truth)
    fig.colorbar(im, ax=b, label="best score over yaw", fraction=0.046, pad=0.03)
    _legend(b, smap, truth is not None)
    a.set_title("over the photo (table plane)", fontsize=9)
    b.set_title("top-down table map", fontsize=9)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return buf.getvalue()


def write_heatmap(path: str | Path, image_rgb, camera: Camera, table: Table, result, truth=None) -> None:
    """--heatmap: the Result's heat map (result.heatmap) as a PNG, written atomically."""
    b, conf = result.best, result.confidence
    title = f"best score over yaw per {result.heatmap.step_m * 100:g} cm cell; answer x {b.x_m:+.3f} m, " \
            f"y {b.y_m:+.3f} m, yaw {math.degrees(b.yaw_rad):.0f} deg"  # fmt: skip
    if conf is not None and conf.margin is not None:
        title += f"; confidence margin {conf.margin:.4f}"
    data = render_heatmap(image_rgb, camera, table, result.heatmap, (b.x_m, b.y_m, b.yaw_rad), title, truth)
    atomic_write(path, lambda f: f.write(data))
