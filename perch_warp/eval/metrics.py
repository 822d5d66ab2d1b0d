"""Errors per target (ADD-S, ADD, translation, yaw, miss class), per_target.csv, the summary and its table."""

from __future__ import annotations

import csv
import io
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .. import bop, pose_error
from ..bop import IMAGE_LABEL_KEYS, Selection, TableCache
from ..errors import PerchError
from ..mesh import load_mesh
from ..outputs import atomic_write_text
from ..table import decompose_on_table
from .journal import Done

ADDS_THRESHOLD_M = 0.02


AUC_MAX_THRESHOLD_M = 0.1


OCCLUSION_BINS = np.linspace(0.0, 1.0, 11)


def miss_class(adds_mm: float, score: float, probe_score: float | None) -> str:
    """ "ok" below 2 cm ADD-S; else a "search miss" when the ground truth's cell scores higher than the
    answer (the score prefers the truth, the search did not find it), else a "score miss" (the score
    itself prefers the wrong place); "" without a probe."""
    if adds_mm < 1000.0 * ADDS_THRESHOLD_M:
        return "ok"
    if probe_score is None or not np.isfinite(probe_score):
        return ""
    return "search miss" if probe_score > score + 1e-6 else "score miss"


class GeometryCache:
    """Model vertices/faces (metres) per object, and the subsampled points for ADD(-S)."""

    def __init__(self, model_paths: dict[int, Path], max_points: int = pose_error.DEFAULT_MAX_POINTS):
        self.model_paths = model_paths
        self.max_points = max_points
        self._cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def get(self, obj_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices_m (N, 3), faces (F, 3), ADD-S points_m (<= max_points, 3))."""
        if obj_id not in self._cache:
            mesh = load_mesh(self.model_paths[obj_id])
            V = np.asarray(mesh.vertices_m, dtype=np.float64)
            self._cache[obj_id] = (V, np.asarray(mesh.faces), pose_error.subsample_points(V, self.max_points))
        return self._cache[obj_id]


def compute_errors(selection: Selection, done: dict, tables: TableCache, geometry: GeometryCache) -> list[dict]:
    """One row per finished target: ADD-S/ADD/translation in mm, yaw error in degrees, and the poses on the table."""
    rows = []
    for im in selection.images:
        table, how = tables.get(im)
        for t in im.targets:
            d = done.get(t.key)
            if d is None:
                continue
            _, _, pts = geometry.get(t.obj_id)
            _, xg, yg, yawg = decompose_on_table(table, t.R_gt, t.t_gt_m)
            try:
                _, xe, ye, yawe = decompose_on_table(table, d.R, d.t_m)
            except PerchError:  # a foreign estimate that is not a rotation: it still gets ADD-S
                xe = ye = yawe = float("nan")
            rows.append(
                {
                    "scene_id": t.scene_id,
                    "im_id": t.im_id,
                    "inst": t.inst,
                    "obj_id": t.obj_id,
                    "visib_fract": t.visib_fract,
                    **{k: t.labels.get(k) for k in IMAGE_LABEL_KEYS},
                    "adds_mm": 1000.0 * pose_error.add_s(d.R, d.t_m, t.R_gt, t.t_gt_m, pts),
                    "add_mm": 1000.0 * pose_error.add(d.R, d.t_m, t.R_gt, t.t_gt_m, pts),
                    "te_mm": 1000.0 * pose_error.translation_error(d.t_m, t.t_gt_m),
                    "yaw_err_deg": math.degrees(pose_error.yaw_error(yawe, yawg))
                    if np.isfinite(yawe)
                    else float("nan"),
                    "x_gt_m": xg,
                    "y_gt_m": yg,
                    "yaw_gt_deg": math.degrees(yawg),
                    "x_est_m": xe,
                    "y_est_m": ye,
                    "yaw_est_deg": math.degrees(yawe),
                    "score": d.score,
                    "time_s": d.time_s,
                    "table": how,
                    "gt_in_region": d.details.get("gt_in_region"),
                    "n_candidates": d.details.get("n_candidates"),
                    "n_evaluated": d.details.get("n_evaluated"),
                    **_diagnostics(d),
                    "rest": d.details.get("rest"),  # the resting pose that won under --rest stable
                    **_joint_columns(d, t, pts),
                    "R_est": d.R,
                    "t_est_m": d.t_m,
                    "R_gt": t.R_gt,
                    "t_gt_m": t.t_gt_m,
                }
            )
    for r in rows:
        r["miss"] = miss_class(r["adds_mm"], r["score"], r["gt_cell_score"])
    return rows


def _diagnostics(d: Done) -> dict:
    """The ground truth's cell (its best score, the answer's margin over it) and the answer's silhouette."""
    probe = d.details.get("probe") or {}
    sil = d.details.get("silhouette") or {}
    conf = d.details.get("confidence") or {}
    cell = probe.get("score")
    return {
        # None when no clearly different pose shows a feature point (the most confident case): see separation.
        "confidence": conf.get("margin"),
        "confidence_exact": conf.get("exact"),
        "confidence_known": bool(conf),
        "gt_cell_score": cell,
        "margin": d.score - cell if cell is not None else None,
        "est_points": sil.get("points"),
        "est_edge_share": sil.get("edge_share"),
    }


def _joint_columns(d: Done, t, pts: np.ndarray) -> dict:
    """Under eval --joint: whether the joint step changed the answer and the ADD-S of the object's own best;
    with --occluders answers, whether the second pass changed it and the first pass's joint answer's ADD-S."""
    out = {}
    for key, changed, adds, R, tr in (
        ("joint", "joint_changed", "own_adds_mm", "own_R_m2c", "own_t_m2c_m"),
        ("occluders", "second_pass_changed", "first_adds_mm", "first_R_m2c", "first_t_m2c_m"),
    ):
        j = d.details.get(key)
        out[changed] = None if j is None else bool(j["changed"])
        out[adds] = None
        if j is not None:
            R_m2c, t_m = np.asarray(j[R], dtype=np.float64), np.asarray(j[tr], dtype=np.float64)
            out[adds] = 1000.0 * pose_error.add_s(R_m2c, t_m, t.R_gt, t.t_gt_m, pts)
    # Each pass's own search time (journals from before stop 59 lack the first pass's)
    occ = d.details.get("occluders") or {}
    out["first_pass_s"] = occ.get("first_total_s")
    out["second_pass_s"] = d.details.get("timings_s", {}).get("total") if "first_total_s" in occ else None
    return out


_PER_TARGET_COLUMNS = [
    "scene_id",
    "im_id",
    "inst",
    "obj_id",
    "visib_fract",
    *IMAGE_LABEL_KEYS,
    "adds_mm",
    "add_mm",
    "te_mm",
    "yaw_err_deg",
    "x_gt_m",
    "y_gt_m",
    "yaw_gt_deg",
    "x_est_m",
    "y_est_m",
    "yaw_est_deg",
    "score",
    "time_s",
    "table",
    "gt_in_region",
    "n_candidates",
    "n_evaluated",
    "gt_cell_score",
    "margin",
    "miss",
    "est_points",
    "est_edge_share",
    "rest",
    "confidence",
    "confidence_exact",
    "joint_changed",
    "own_adds_mm",
    "second_pass_changed",
    "first_adds_mm",
    "first_pass_s",
    "second_pass_s",
]


def write_per_target(path: Path, rows: list[dict], failed: Sequence[dict] = ()) -> None:
    """per_target.csv: errors in mm / degrees, table-frame poses in metres / degrees; then the failed
    targets, their ids and `failure` (the reason) only. Written atomically."""

    columns = [*_PER_TARGET_COLUMNS, "failure"]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(columns)
    for r in [*rows, *failed]:
        w.writerow(["" if r.get(c) is None else (f"{r[c]:.10g}" if isinstance(r[c], float) else r[c]) for c in columns])

    atomic_write_text(path, buf.getvalue())


def _metrics(rows: list[dict]) -> dict:
    adds_m = np.array([r["adds_mm"] for r in rows], dtype=np.float64) / 1000.0
    add_m = np.array([r["add_mm"] for r in rows], dtype=np.float64) / 1000.0
    te = np.array([r["te_mm"] for r in rows], dtype=np.float64)
    yaw = np.array([r["yaw_err_deg"] for r in rows], dtype=np.float64)
    times = np.array([r["time_s"] for r in rows], dtype=np.float64)

    def stat(fn, a):
        a = a[np.isfinite(a)]
        return float(fn(a)) if a.size else None

    return {
        "n": len(rows),
        "auc": pose_error.auc(adds_m, AUC_MAX_THRESHOLD_M),
        "auc_posecnn": pose_error.auc_posecnn(adds_m, AUC_MAX_THRESHOLD_M),
        "adds_below_2cm_pct": pose_error.accuracy_below(adds_m, ADDS_THRESHOLD_M),
        "auc_add": pose_error.auc(add_m, AUC_MAX_THRESHOLD_M),
        "te_below_1cm_pct": pose_error.accuracy_below(te / 1000.0, 0.01),
        "misses": {c: sum(1 for r in rows if r.get("miss") == c) for c in ("search miss", "score miss")},
        "mean_adds_mm": stat(np.mean, adds_m * 1000.0),
        "median_adds_mm": stat(np.median, adds_m * 1000.0),
        "mean_te_mm": stat(np.mean, te),
        "median_te_mm": stat(np.median, te),
        "mean_yaw_err_deg": stat(np.mean, yaw),
        "median_yaw_err_deg": stat(np.median, yaw),
        "mean_time_s": stat(np.mean, times),
        "gt_outside_region": sum(1 for r in rows if r["gt_in_region"] is False),
    }


def separation(margins: Sequence[float | None], right: Sequence[bool], shares=(0.5, 0.8)) -> dict:
    """How well a confidence separates right from wrong answers: the accuracy (%) of the most confident
    share of them (ceil(share * n) answers, highest margin first, ties in the given order) for each share,
    of all of them, and the ROC AUC (the chance that a right answer's margin exceeds a wrong one's, ties
    counting half: the Mann-Whitney statistic); None where undefined (no answer; ROC AUC with all right or
    all wrong). A margin of None (no clearly different pose to compare with) ranks above every number."""
    from scipy.stats import rankdata

    m = np.array([np.inf if v is None else v for v in margins], dtype=np.float64)
    ok = np.asarray(right, dtype=bool)
    n, n_right = len(m), int(ok.sum())
    out: dict = {"n": n, "n_right": n_right, "n_wrong": n - n_right, "accuracy_pct": None, "roc_auc": None}
    if n == 0:
        return out | {f"top{round(100 * s)}_accuracy_pct": None for s in shares}
    order = np.argsort(-m, kind="stable")
    for s in shares:
        k = max(1, math.ceil(s * n - 1e-9))
        out[f"top{round(100 * s)}_accuracy_pct"] = float(100.0 * ok[order[:k]].mean())
    out["accuracy_pct"] = float(100.0 * ok.mean())
    if 0 < n_right < n:
        ranks = rankdata(m)  # average ranks: ties count half
        out["roc_auc"] = float((ranks[ok].sum() - n_right * (n_right + 1) / 2) / (n_right * (n - n_right)))
    return out


def confidence_separation(rows: list[dict]) -> dict | None:
    """`separation` of the pooled targets that have a confidence (right: ADD-S < 2 cm); None without any."""
    rs = [r for r in rows if r.get("confidence_known")]
    if not rs:
        return None
    return separation([r["confidence"] for r in rs], [r["adds_mm"] < 1000.0 * ADDS_THRESHOLD_M for r in rs])


def summarize(rows: list[dict], ds: bop.Dataset, selection: Selection) -> dict:
    """Metrics per object, their mean over objects (thesis Table 4.1's "All Objects"), and pooled over targets."""
    by_obj: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_obj[r["obj_id"]].append(r)
    objects = {}
    for obj_id in sorted(by_obj):
        m = _metrics(by_obj[obj_id])
        m["name"] = ds.object_name(obj_id)
        objects[str(obj_id)] = m
    keys = ("auc", "auc_posecnn", "adds_below_2cm_pct")
    mean_over_objects = {k: float(np.mean([o[k] for o in objects.values()])) if objects else None for k in keys}
    pooled = _metrics(rows) if rows else {}
    summary = {
        "metric": "ADD-S",
        "auc_max_threshold_m": AUC_MAX_THRESHOLD_M,
        "adds_threshold_m": ADDS_THRESHOLD_M,
        "n_images": len(selection.images),
        "n_targets": len(selection.targets),
        "n_evaluated": len(rows),
        "skipped_no_model": {str(k): v for k, v in sorted(selection.skipped_no_model.items())},
        "objects": objects,
        "all_objects": mean_over_objects,
        "pooled": pooled,
        "pooled_ci95": pooled_intervals(rows) if rows else {},
        "mean_runtime_s_per_target": pooled.get("mean_time_s"),
    }
    occ = occlusion_accuracy(rows)
    if occ is not None:
        summary["occlusion"] = occ
    sep = confidence_separation(rows)
    if sep is not None:
        summary["confidence_separation"] = sep
    by_label = label_metrics(rows)
    if by_label:
        summary["by_label"] = by_label
    joint = joint_summary(rows)
    if joint is not None:
        summary["joint"] = joint
    second = occluders_summary(rows)
    if second is not None:
        summary["occluders"] = second
    return summary


def _paired_note(j: dict, what: str, a: str, b: str) -> str:
    """paired_summary's result in one sentence (a: the base's name, b: the answers')."""
    better = sum(c["adds_mm"] < c[f"{a}_adds_mm"] for c in j["changed"])
    lo, hi = j["auc_gain_ci95"]
    return (
        f"{what}: changed {j['n_changed']} of {j['n']} answers ({better} closer to the truth); ADD-S AUC "
        f"{j[a]['auc']:.2f} -> {j[b]['auc']:.2f} (paired gain {j['auc_gain']:+.2f}, 95 % CI {lo:+.2f}..{hi:+.2f}); "
        f"< 2 cm {j[a]['adds_below_2cm_pct']:.1f} -> {j[b]['adds_below_2cm_pct']:.1f} %."
    )


def mean_interval(values: np.ndarray, n_boot: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """95 % percentile bootstrap interval of a mean over targets (targets resampled with replacement, a
    fixed seed so a summary is reproducible); of paired differences when `values` are differences."""
    values = np.asarray(values, dtype=np.float64)
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, len(values), (n_boot, len(values)))].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def target_shares(adds_m, add_m, te_m) -> dict[str, np.ndarray]:
    """Each target's share (%) of the four pooled accuracy figures, whose means they are: the exact ADD-S
    AUC, ADD-S < 2 cm, the exact ADD AUC and translation error < 1 cm (pose_error.auc_shares,
    below_shares). Errors in metres; a failed target (NaN, inf, None) shares nothing."""
    return {
        "auc": pose_error.auc_shares(adds_m, AUC_MAX_THRESHOLD_M),
        "adds_below_2cm_pct": pose_error.below_shares(adds_m, ADDS_THRESHOLD_M),
        "auc_add": pose_error.auc_shares(add_m, AUC_MAX_THRESHOLD_M),
        "te_below_1cm_pct": pose_error.below_shares(te_m, 0.01),
    }


def pooled_intervals(rows: list[dict]) -> dict[str, tuple[float, float]]:
    """`mean_interval` of each of the four pooled accuracy figures (see `target_shares`)."""
    shares = target_shares(
        [r["adds_mm"] / 1000.0 for r in rows], [r["add_mm"] / 1000.0 for r in rows], [r["te_mm"] / 1000.0 for r in rows]
    )
    return {k: mean_interval(v) for k, v in shares.items()}


def joint_summary(rows: list[dict]) -> dict | None:
    """eval --joint, paired per target: the objects' own answers against the joint step's (ADD-S AUC and
    < 2 cm, with 95 % bootstrap intervals of the differences), and each changed target; None otherwise."""
    return paired_summary(rows, "own_adds_mm", "joint_changed", ("own", "joint"))


def occluders_summary(rows: list[dict]) -> dict | None:
    """eval --joint --occluders answers, paired per target: the first pass's joint answers against the
    second pass's (what the other answers hide left out), as joint_summary, and what each pass's own
    searches cost over the targets whose journal has both times ("cost"); None otherwise."""
    out = paired_summary(rows, "first_adds_mm", "second_pass_changed", ("first_pass", "second_pass"))
    timed = [r for r in rows if r.get("first_pass_s") is not None and r.get("second_pass_s") is not None]
    if out is not None and timed:
        out["cost"] = {
            "n": len(timed),
            "first_pass_s": float(sum(r["first_pass_s"] for r in timed)),
            "second_pass_s": float(sum(r["second_pass_s"] for r in timed)),
        }
    return out


def paired_summary(rows: list[dict], base_col: str, changed_col: str, names: tuple[str, str]) -> dict | None:
    """Rows' ADD-S (adds_mm) against another answer's on the same targets (base_col): AUC and < 2 cm of
    each (names: base's, then the rows'), the paired gains with 95 % bootstrap intervals, the changed
    targets (changed_col); None when no row has base_col."""
    rs = [r for r in rows if r.get(base_col) is not None]
    if not rs:
        return None
    base = np.array([r[base_col] for r in rs]) / 1000.0
    now = np.array([r["adds_mm"] for r in rs]) / 1000.0

    d_auc = pose_error.auc_shares(now, AUC_MAX_THRESHOLD_M) - pose_error.auc_shares(base, AUC_MAX_THRESHOLD_M)
    d_ok = pose_error.below_shares(now, ADDS_THRESHOLD_M) - pose_error.below_shares(base, ADDS_THRESHOLD_M)
    changed = [r for r in rs if r[changed_col]]
    return {
        "n": len(rs),
        "n_changed": len(changed),
        **{
            name: {
                "auc": pose_error.auc(e, AUC_MAX_THRESHOLD_M),
                "adds_below_2cm_pct": pose_error.accuracy_below(e, ADDS_THRESHOLD_M),
            }
            for name, e in zip(names, (base, now), strict=True)
        },
        "auc_gain": float(d_auc.mean()),
        "auc_gain_ci95": mean_interval(d_auc),
        "below_2cm_gain_pct": float(d_ok.mean()),
        "below_2cm_gain_ci95": mean_interval(d_ok),
        "changed": [
            {
                "key": [r["scene_id"], r["im_id"], r["inst"]],
                "obj_id": r["obj_id"],
                f"{names[0]}_adds_mm": r[base_col],
                "adds_mm": r["adds_mm"],
            }
            for r in changed
        ],
    }


def label_metrics(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """Metrics of the targets pooled over objects, per value of each image label that occurs.

    Values keep their order of first appearance (scene, image order), so a generator's
    "normal" before "harsh" stays that way; targets without a key are left out of its split.
    """
    out: dict[str, dict[str, dict]] = {}
    for key in IMAGE_LABEL_KEYS:
        groups: dict[str, list[dict]] = {}
        for r in rows:
            value = r.get(key)
            if value is not None:
                groups.setdefault(value, []).append(r)
        if groups:
            out[key] = {value: _metrics(rs) for value, rs in groups.items()}
    return out


def occlusion_accuracy(rows: list[dict]) -> dict | None:
    """ADD-S < 2 cm accuracy (%) in bins of occlusion = 1 - visib_fract; None without visib_fract."""
    rows = [r for r in rows if r["visib_fract"] is not None]
    if not rows:
        return None

    def binned(rs):
        occ = np.array([1.0 - r["visib_fract"] for r in rs])
        ok = np.array([r["adds_mm"] < ADDS_THRESHOLD_M * 1000.0 for r in rs])
        idx = np.clip(np.digitize(occ, OCCLUSION_BINS[1:-1]), 0, len(OCCLUSION_BINS) - 2)
        n = np.bincount(idx, minlength=len(OCCLUSION_BINS) - 1)
        hits = np.bincount(idx, weights=ok.astype(float), minlength=len(OCCLUSION_BINS) - 1)
        acc = [float(100.0 * h / k) if k else None for h, k in zip(hits, n, strict=True)]
        return {"n": n.tolist(), "accuracy_pct": acc}

    by_obj: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_obj[r["obj_id"]].append(r)
    return {
        "bin_edges_occlusion": OCCLUSION_BINS.tolist(),
        "all": binned(rows),
        "objects": {str(k): binned(v) for k, v in sorted(by_obj.items())},
    }


def format_table(summary: dict) -> str:
    """The summary as thesis Table 4.1: AUC and ADD-S < 2 cm per object, all objects, mean runtime."""
    lines = [f"{'objects':<26}{'n':>6}{'AUC':>9}{'<2cm':>9}{'te med mm':>11}{'yaw med deg':>13}"]
    lines.append("-" * len(lines[0]))

    def fmt(v, spec):
        return format(v, spec) if v is not None and np.isfinite(v) else "-"

    for obj in summary["objects"].values():
        lines.append(
            f"{obj['name'][:25]:<26}{obj['n']:>6}{fmt(obj['auc'], '9.2f')}"
            f"{fmt(obj['adds_below_2cm_pct'], '9.2f')}"
            f"{fmt(obj['median_te_mm'], '11.1f')}{fmt(obj['median_yaw_err_deg'], '13.1f')}"
        )
    lines.append("-" * len(lines[0]))
    a, p = summary["all_objects"], summary["pooled"]
    lines.append(f"{'All Objects (mean)':<26}{'':>6}{fmt(a['auc'], '9.2f')}{fmt(a['adds_below_2cm_pct'], '9.2f')}")
    if p:
        lines.append(
            f"{'All targets (pooled)':<26}{p['n']:>6}{fmt(p['auc'], '9.2f')}"
            f"{fmt(p['adds_below_2cm_pct'], '9.2f')}"
            f"{fmt(p['median_te_mm'], '11.1f')}{fmt(p['median_yaw_err_deg'], '13.1f')}"
        )
    by_label = summary.get("by_label") or {}
    if by_label:
        # Below the All Objects mean, so that row still reads as the mean of the object rows above it.
        lines.append("-" * len(lines[0]))
        for key, values in by_label.items():
            for value, m in values.items():
                lines.append(
                    f"{f'{key} = {value}'[:25]:<26}{m['n']:>6}{fmt(m['auc'], '9.2f')}"
                    f"{fmt(m['adds_below_2cm_pct'], '9.2f')}"
                    f"{fmt(m['median_te_mm'], '11.1f')}{fmt(m['median_yaw_err_deg'], '13.1f')}"
                )
        lines.append("-" * len(lines[0]))
    rt = summary.get("mean_runtime_s_per_target")
    lines.append(f"{'Mean Runtime':<26}{'':>6}{fmt(rt, '8.1f')}s per target")
    return "\n".join(lines + _table_notes(summary, fmt))


def _table_notes(summary: dict, fmt) -> list[str]:
    """The lines under the table: what the columns mean, skipped and failed targets, miss classes."""
    p, by_label = summary["pooled"], summary.get("by_label") or {}
    notes = ["ADD-S AUC over 0-10 cm (exact area, %); <2cm: % of targets with ADD-S < 2 cm."]
    if by_label:
        notes.append("Label rows (e.g. lighting = harsh): targets of all objects, by their image's scene_camera label.")
    skipped = summary.get("skipped_no_model") or {}
    if skipped:
        notes.append(f"Skipped (no mesh): {sum(skipped.values())} instances of objects {', '.join(skipped)}.")
    if p:
        notes.append(
            f"Pooled ADD AUC {fmt(p.get('auc_add'), '.2f')}; translation error < 1 cm: "
            f"{fmt(p.get('te_below_1cm_pct'), '.2f')} %."
        )
        ci = summary.get("pooled_ci95") or {}
        if ci:
            notes.append(
                "95 % bootstrap intervals (targets resampled): AUC {}, <2cm {}, ADD AUC {}, te < 1 cm {}.".format(
                    *(
                        f"{ci[k][0]:.1f}-{ci[k][1]:.1f}"
                        for k in ("auc", "adds_below_2cm_pct", "auc_add", "te_below_1cm_pct")
                    )
                )
            )
        misses = p.get("misses") or {}
        if any(misses.values()):
            notes.append(
                f"Misses (>= 2 cm): {misses.get('score miss', 0)} score misses (the answer outscores the ground "
                f"truth's cell), {misses.get('search miss', 0)} search misses (the truth's cell scores higher)."
            )
    sep = summary.get("confidence_separation")
    if sep:
        auc = "n/a (all right or all wrong)" if sep["roc_auc"] is None else f"{sep['roc_auc']:.3f}"
        notes.append(
            f"Confidence (margin, right = ADD-S < 2 cm): the most confident 50 % are "
            f"{fmt(sep['top50_accuracy_pct'], '.1f')} % right, 80 %: {fmt(sep['top80_accuracy_pct'], '.1f')} %, "
            f"all: {fmt(sep['accuracy_pct'], '.1f')} %; ROC AUC {auc} (n = {sep['n']})."
        )
    for key, what, a, b in (
        ("joint", "Joint step (eval --joint)", "own", "joint"),
        ("occluders", "Second pass (--occluders answers)", "first_pass", "second_pass"),
    ):
        if summary.get(key):
            notes.append(_paired_note(summary[key], what, a, b))
    cost = (summary.get("occluders") or {}).get("cost")
    if cost:
        share = 100.0 * cost["second_pass_s"] / cost["first_pass_s"] if cost["first_pass_s"] > 0 else float("nan")
        notes.append(
            f"Second pass cost: its searches took {cost['second_pass_s']:.0f} s against the first pass's "
            f"{cost['first_pass_s']:.0f} s ({share:.0f} %) over {cost['n']} targets."
        )
    outside = p.get("gt_outside_region") if p else 0
    if outside:
        notes.append(f"{outside} targets lie outside their search region.")
    if summary.get("n_gt_rotations_projected"):
        notes.append(
            f"{summary['n_gt_rotations_projected']} ground-truth rotations were near-orthonormal and projected "
            f"onto SO(3) (tolerance max |R R^T - I| <= {summary['gt_rotation_tolerance']:g})."
        )
    if summary.get("n_failed"):
        notes.append(f"FAILED: {summary['n_failed']} targets (reasons in per_target.csv and summary.json).")
    return notes
