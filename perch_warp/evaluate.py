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

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import bop, pose_error
from .bop import IMAGE_LABEL_KEYS, Selection, TableCache, Target, select_targets
from .camera import Camera
from .errors import PerchError
from .table import RestingPose, Table, decompose_on_table

ADDS_THRESHOLD_M = 0.02
AUC_MAX_THRESHOLD_M = 0.1
OCCLUSION_BINS = np.linspace(0.0, 1.0, 11)
CONFIG_FILE = "eval_config.json"
JOURNAL_FILE = "targets.jsonl"
RESULTS_FILE = "results.csv"

# Arguments that choose what to evaluate or where to write, not how to search:
# changing them between runs of one OUTDIR is fine.
_NOT_SEARCH_OPTIONS = {
    "out",
    "restart",
    "max_images",
    "scenes",
    "objects",
    "gallery",
    "no_plots",
    "device",
    "func",
    "command",
    "quiet",
    "verbose",
    "progress",
    "top_k",
    "batch_pixels",
    "cpu_threads",  # the scores do not depend on the number of CPU threads
    "max_candidates",  # a guard, not a search setting
}
# Recorded separately in eval_config.json.
_EVAL_ARGS = {"dataset", "split", "models", "table_source"}


# ----------------------------------------------------------------------------- targets


# ----------------------------------------------------------------------------- estimator


@dataclass
class Estimate:
    """A model -> camera pose (metres) with the searcher's score and free-form details."""

    R_m2c: np.ndarray
    t_m2c_m: np.ndarray
    score: float
    details: dict = field(default_factory=dict)


#: (target, image_rgb uint8 HxWx3, camera, table, resting, space) -> Estimate
Estimator = Callable[[Target, np.ndarray, Camera, Table, RestingPose, object], Estimate]
#: (camera, table, resting) -> search space (must not look at the ground-truth x, y, yaw)
SpaceFn = Callable[[Camera, Table, RestingPose], object]


class EngineEstimator:
    """The real search: one `Engine` per object, built on first use (outside the timed call)."""

    def __init__(
        self, model_paths: dict[int, Path], weights_spec: str = "auto", device: str | None = None, config=None
    ):
        self.model_paths = model_paths
        self.weights_spec = weights_spec
        self.device = device
        self.config = config  # EngineConfig, None: its defaults
        self._weights = None
        self._engines: dict[int, object] = {}

    def prepare(self, obj_id: int) -> None:
        if obj_id in self._engines:
            return
        from .engine import Engine
        from .features import load_feature_weights
        from .mesh import load_mesh

        if self._weights is None:
            self._weights = load_feature_weights(self.weights_spec)
        mesh = load_mesh(self.model_paths[obj_id])
        self._engines[obj_id] = Engine(mesh, self._weights, self.device, self.config)

    def __call__(self, target: Target, image_rgb, camera, table, resting, space) -> Estimate:
        self.prepare(target.obj_id)
        engine = self._engines[target.obj_id]
        # Diagnostics only: the ground truth's cell is scored after the search, on the same photo.
        _, xg, yg, yawg = decompose_on_table(table, target.R_gt, target.t_gt_m)
        res = engine.estimate(image_rgb, camera, table, resting, space, progress=False, probe=(xg, yg, yawg))
        T = np.asarray(res.T_m2c, dtype=np.float64)
        details = {
            "n_candidates": int(res.n_candidates),
            "n_evaluated": int(res.info.get("evaluated", res.n_candidates)),  # scored: fewer when pruned
            "timings_s": {k: float(v) for k, v in res.timings.items()},
            "device": res.device,
            "top_k": [{"x_m": c.x_m, "y_m": c.y_m, "yaw_rad": c.yaw_rad, "score": c.score} for c in res.top_k],
        }
        if "refine" in res.info:  # where the refinement started (the grid's best) and how far it went
            details["refine"] = res.info["refine"]
        details["probe"] = res.info["probe"]
        details["silhouette"] = silhouette_points(engine, camera, T)
        return Estimate(T[:3, :3], T[:3, 3], float(res.score), details)


def silhouette_points(engine, camera: Camera, T_m2c: np.ndarray) -> dict:
    """A pose's silhouette on the engine's feature grid: its feature points (window centres on the
    rendered mask, inside the photo) and the share of them at the edge (whose window is not wholly on
    the mask: those compared with windows composited with the photo)."""
    from scipy.ndimage import binary_erosion

    _, mask = engine.render(camera, T_m2c)
    ks, s = engine.weights.kernel_size, engine.config.stride
    half = ks // 2
    inner = binary_erosion(mask, np.ones((ks, ks), bool), border_value=0)
    centres = np.zeros_like(mask)
    centres[half : camera.height - half : s, half : camera.width - half : s] = True
    n = int((mask & centres).sum())
    edge = int((mask & centres & ~inner).sum())
    return {"points": n, "edge_share": edge / n if n else float("nan")}


def miss_class(adds_mm: float, score: float, probe_score: float | None) -> str:
    """ "ok" below 2 cm ADD-S; else a "search miss" when the ground truth's cell scores higher than the
    answer (the score prefers the truth, the search did not find it), else a "score miss" (the score
    itself prefers the wrong place); "" without a probe."""
    if adds_mm < 1000.0 * ADDS_THRESHOLD_M:
        return "ok"
    if probe_score is None or not np.isfinite(probe_score):
        return ""
    return "search miss" if probe_score > score + 1e-6 else "score miss"


def visible_table_space(
    xy_step_m: float = 0.01, yaw_step_rad: float = math.radians(5.0), clip_m: float = 1.0
) -> SpaceFn:
    """The default region: the table the image sees, clipped to clip_m x clip_m (no ground truth used)."""
    from .search_space import SearchSpace

    def space_fn(camera: Camera, table: Table, resting: RestingPose):
        return SearchSpace.visible_table(camera, table, xy_step_m=xy_step_m, yaw_step_rad=yaw_step_rad, clip_m=clip_m)

    return space_fn


# ----------------------------------------------------------------------------- resume state


@dataclass
class Done:
    """A finished target: its estimate, as read back from results.csv or the journal."""

    obj_id: int
    R: np.ndarray
    t_m: np.ndarray
    score: float
    time_s: float
    details: dict = field(default_factory=dict)


def _repair_journal(out_dir: Path) -> None:
    """Cut off a last journal line torn by a crash (no final newline), so that the next record is not
    appended onto it; the cut target's row in results.csv, if written, still counts, else it runs again."""
    path = out_dir / JOURNAL_FILE
    if not path.exists():
        return
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return
    keep = data.rfind(b"\n") + 1
    with open(path, "r+b") as f:
        f.truncate(keep)
        f.flush()
        os.fsync(f.fileno())
    print(
        f"warning: {path} ended in an incomplete line ({len(data) - keep} bytes, left by an interrupted run): "
        "cut off; its target counts only if results.csv has it",
        file=sys.stderr,
    )


def _load_state(out_dir: Path, selection: Selection) -> tuple[dict, list[bop.BopResult], dict]:
    """Finished targets keyed (scene, im, inst), results.csv rows that match no current target, and the
    targets whose last journal record is a failure (key -> reason).

    Rows are matched to targets by order: the k-th row of object o in an image is the
    k-th instance of o in scene_gt.json. Per-target times come from the journal; rows
    without a journal line get an equal share of their image's time.
    """
    done: dict[tuple[int, int, int], Done] = {}
    foreign: list[bop.BopResult] = []
    results_path = out_dir / RESULTS_FILE
    if results_path.exists():
        rows = bop.read_results(results_path)
        by_image: dict[tuple[int, int], list[bop.BopResult]] = defaultdict(list)
        for r in rows:
            by_image[(r.scene_id, r.im_id)].append(r)
        insts: dict[tuple[int, int, int], list[int]] = defaultdict(list)
        for t in selection.targets:
            insts[(t.scene_id, t.im_id, t.obj_id)].append(t.inst)
        # Instances of each object in an image, in scene_gt order, are matched to rows in file order.
        for (scene_id, im_id), im_rows in by_image.items():
            used: Counter = Counter()
            for r in im_rows:
                cand = insts.get((scene_id, im_id, r.obj_id), [])
                k = used[r.obj_id]
                used[r.obj_id] += 1
                if k < len(cand):
                    share = r.time_s / len(im_rows) if r.time_s >= 0 else float("nan")
                    done[(scene_id, im_id, cand[k])] = Done(r.obj_id, r.R, r.t_mm / 1000.0, r.score, share)
                else:
                    foreign.append(r)
    failed: dict[tuple[int, int, int], str] = {}
    journal = out_dir / JOURNAL_FILE
    if journal.exists():
        for no, line in enumerate(journal.read_text().splitlines(), start=1):
            if not line.strip():
                continue
            try:
                j = json.loads(line)
                key = (int(j["scene_id"]), int(j["im_id"]), int(j["inst"]))
                if "failed" in j:
                    if key not in done:
                        failed[key] = str(j["failed"])
                    continue
                d = Done(
                    int(j["obj_id"]),
                    np.asarray(j["R"], dtype=np.float64).reshape(3, 3),
                    np.asarray(j["t_mm"], dtype=np.float64).reshape(3) / 1000.0,
                    float(j["score"]),
                    float(j["time_s"]),
                    j.get("details", {}),
                )
            except (ValueError, KeyError, TypeError) as e:
                # Torn tails are cut before a run (_repair_journal); this is damage inside the file.
                print(
                    f"warning: {journal} line {no} unreadable ({e}): skipped (its target counts if results.csv "
                    "has it, else it runs again)",
                    file=sys.stderr,
                )
                continue
            done[key] = d
            failed.pop(key, None)
    return done, foreign, failed


def _write_results(out_dir: Path, selection: Selection, done: dict, foreign: list[bop.BopResult]) -> None:
    """Rewrite results.csv from the state: per-image time = sum of its targets' times (BOP needs it equal per image)."""
    order = {t.key: i for i, t in enumerate(selection.targets)}
    rows: list[tuple[tuple, bop.BopResult]] = []
    image_time: dict[tuple[int, int], float] = defaultdict(float)
    for key, d in done.items():
        if np.isfinite(d.time_s):
            image_time[key[:2]] += d.time_s
    for r in foreign:
        if r.time_s >= 0:
            image_time[(r.scene_id, r.im_id)] += r.time_s / max(
                1, sum(1 for f in foreign if (f.scene_id, f.im_id) == (r.scene_id, r.im_id))
            )
    for key, d in done.items():
        res = bop.BopResult(key[0], key[1], d.obj_id, d.score, d.R, d.t_m * 1000.0, image_time.get(key[:2], -1.0))
        rows.append(((key[0], key[1], order.get(key, 10**9), key[2]), res))
    for i, r in enumerate(foreign):
        t = image_time.get((r.scene_id, r.im_id), r.time_s)
        rows.append(
            ((r.scene_id, r.im_id, 10**9 + i, 0), bop.BopResult(r.scene_id, r.im_id, r.obj_id, r.score, r.R, r.t_mm, t))
        )
    rows.sort(key=lambda kr: kr[0])
    bop.write_results(out_dir / RESULTS_FILE, [r for _, r in rows])


def _append_failure(out_dir: Path, target: Target, reason: str) -> None:
    """Journal a failed target: its key and the one-line reason (it is tried again on a rerun)."""
    record = {"scene_id": target.scene_id, "im_id": target.im_id, "inst": target.inst, "obj_id": target.obj_id}
    _append_line(out_dir, json.dumps({**record, "failed": " ".join(reason.split())}))


def _append_line(out_dir: Path, line: str) -> None:
    with open(out_dir / JOURNAL_FILE, "a") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())


def _append_journal(out_dir: Path, target: Target, d: Done) -> None:
    line = json.dumps(
        {
            "scene_id": target.scene_id,
            "im_id": target.im_id,
            "inst": target.inst,
            "obj_id": target.obj_id,
            "score": d.score,
            "time_s": d.time_s,
            "R": d.R.reshape(9).tolist(),
            "t_mm": (d.t_m * 1000.0).tolist(),
            "details": d.details,
        },
        default=_json_default,
    )
    _append_line(out_dir, line)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _check_config(out_dir: Path, config: dict, restart: bool) -> None:
    """Refuse to mix results of different search settings in one OUTDIR."""
    path = out_dir / CONFIG_FILE
    config = json.loads(json.dumps(config, default=_json_default))  # tuples vs lists, as read back
    if restart:
        for name in (RESULTS_FILE, JOURNAL_FILE, CONFIG_FILE):
            (out_dir / name).unlink(missing_ok=True)
    elif path.exists() and ((out_dir / RESULTS_FILE).exists() or (out_dir / JOURNAL_FILE).exists()):
        old = bop.read_json(path, "evaluation settings")
        if not isinstance(old, dict):
            raise PerchError(f"{path} is not an evaluation settings file: use another --out, or --restart")
        diffs = _setting_diffs(old, config)
        if diffs:
            raise PerchError(
                f"{out_dir} holds results made with other settings: {'; '.join(diffs)}; "
                "use another --out, or --restart to start over"
            )
    from .outputs import atomic_write_text

    atomic_write_text(path, json.dumps(config, indent=1, default=_json_default) + "\n")


def _setting_diffs(old: dict, new: dict) -> list[str]:
    """Changed settings as options, briefly: ["--xy-step 0.01 then, 0.02 now", ...]; options that do not
    change scores (_NOT_SEARCH_OPTIONS, e.g. --cpu-threads, also in files written before they were
    ignored) are left out."""

    def flat(c: dict) -> dict:
        out = {k: v for k, v in c.items() if k != "options"}
        out.update({k: v for k, v in (c.get("options") or {}).items() if k not in _NOT_SEARCH_OPTIONS})
        return out

    a, b = flat(old), flat(new)

    def short(v) -> str:
        text = json.dumps(v)
        return text if len(text) <= 40 else text[:37] + "..."

    names = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    return [f"--{k.replace('_', '-')} {short(a.get(k))} then, {short(b.get(k))} now" for k in names]


# ----------------------------------------------------------------------------- the run


def evaluate(
    dataset_dir: str | Path,
    out_dir: str | Path,
    *,
    make_estimator: Callable[[dict[int, Path]], Estimator],
    space_fn: SpaceFn,
    split: str = "test",
    scenes: Sequence[int] | None = None,
    objects: Sequence[int] | None = None,
    max_images: int | None = None,
    models_dir: str | Path | None = None,
    table_source: str = "auto",
    options: dict | None = None,
    restart: bool = False,
    progress: bool = True,
    plots: bool = True,
    gallery: int = 4,
    max_points: int = pose_error.DEFAULT_MAX_POINTS,
    command: str = "",
) -> dict:
    """Run (or continue) the evaluation and write every output; returns the summary dict.

    `make_estimator(mesh paths by object id)` is called once, only when targets remain;
    the estimator it returns is called once per unfinished target, and `space_fn` gives
    its search region. `options` (JSON)
    are the search settings, recorded in eval_config.json and checked on resume.
    """

    from .outputs import check_output_dir, folder_lock

    out_dir = check_output_dir(out_dir, "--out")
    ds = bop.open_dataset(dataset_dir, split, models_dir)
    selection = select_targets(ds, scenes, objects, max_images, table_source)
    if not selection.targets:
        raise PerchError(f"no targets: no instance of objects {sorted(objects or [])} with a mesh in {ds.split_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    with folder_lock(out_dir, "OUTDIR"):
        return _evaluate_locked(
            ds, selection, out_dir, make_estimator, space_fn, split, table_source, options, restart, progress,
            plots, gallery, max_points, command, dataset_dir,
        )  # fmt: skip


def _evaluate_locked(
    ds, selection, out_dir, make_estimator, space_fn, split, table_source, options, restart, progress, plots,
    gallery, max_points, command, dataset_dir,
) -> dict:  # fmt: skip
    """`evaluate` once OUTDIR is locked: the state, the loop over targets and the outputs."""
    from .image import load_rgb

    config = {
        "dataset": str(Path(dataset_dir).resolve()),
        "split": split,
        "table_source": table_source,
        "options": options or {},
    }
    _check_config(out_dir, config, restart)
    _repair_journal(out_dir)
    done, foreign, failed = _load_state(out_dir, selection)
    tables = TableCache(table_source)

    todo = [(im, t) for im in selection.images for t in im.targets if t.key not in done]
    n_before = len(selection.targets) - len(todo)
    estimator = None
    if n_before and todo:
        print(f"resuming: {n_before} of {len(selection.targets)} targets already done in {out_dir}", file=sys.stderr)

    from tqdm import tqdm

    bar = tqdm(total=len(todo), unit="target", desc="eval", disable=not progress or not todo, dynamic_ncols=True)
    current: tuple | None = None
    image = None
    try:
        for im, target in todo:
            # One bad target must not stop a long evaluation: whatever fails in it (its ground truth, its
            # table, its search) is journalled as its failure and the run goes on. Options that would fail
            # every target alike (SearchTooLarge) and interruptions still stop the run.
            try:
                if target.problem:
                    raise PerchError(target.problem)
                if current != (im.scene_id, im.im_id):
                    image = None
                    image = load_rgb(im.rgb)
                    current = (im.scene_id, im.im_id)
                if image is None:
                    raise PerchError(f"image {im.rgb} could not be read (see the image's first target)")
                table, table_how = tables.get(im)
                resting, _, _, _ = decompose_on_table(table, target.R_gt, target.t_gt_m)
                space = space_fn(im.camera, table, resting)
                if estimator is None:
                    estimator = make_estimator(selection.model_paths)
                prepare = getattr(estimator, "prepare", None)
                if callable(prepare):
                    prepare(target.obj_id)  # building the engine is not part of the per-target runtime
                t0 = time.perf_counter()
                est = estimator(target, image, im.camera, table, resting, space)
                dt = time.perf_counter() - t0
                details = dict(est.details)
                details["table"] = table_how
                details.update(_space_details(space, table, target))
                d = Done(
                    target.obj_id,
                    np.asarray(est.R_m2c, dtype=np.float64).reshape(3, 3),
                    np.asarray(est.t_m2c_m, dtype=np.float64).reshape(3),
                    float(est.score),
                    dt,
                    details,
                )
            except Exception as e:  # noqa: BLE001 - recorded with its reason; see above
                if _stops_the_run(e):
                    raise
                reason = str(e) if isinstance(e, PerchError) else f"{type(e).__name__}: {e}"
                failed[target.key] = " ".join(reason.split())
                _append_failure(out_dir, target, reason)
                print(f"target {target.key} (obj {target.obj_id}) failed: {failed[target.key]}", file=sys.stderr)
                bar.update(1)
                continue
            # Journal first: if the rewrite below is interrupted, the journal still has the target.
            _append_journal(out_dir, target, d)
            done[target.key] = d
            failed.pop(target.key, None)
            _write_results(out_dir, selection, done, foreign)
            bar.set_postfix_str(f"{target.scene_id}/{target.im_id} obj {target.obj_id} {dt:.1f}s")
            bar.update(1)
    finally:
        bar.close()
    _write_results(out_dir, selection, done, foreign)  # canonical order, also when nothing was left to do

    geometry = GeometryCache(selection.model_paths, max_points)
    rows = compute_errors(selection, done, tables, geometry)
    write_per_target(out_dir / "per_target.csv", rows, _failed_rows(selection, failed))
    summary = summarize(rows, ds, selection)
    summary["n_failed"] = len(failed)
    summary["failed"] = [{"key": list(k), "reason": r} for k, r in sorted(failed.items())]
    summary["n_gt_rotations_projected"] = sum(t.gt_projected for t in selection.targets)
    summary["gt_rotation_tolerance"] = bop.GT_ROTATION_TOLERANCE
    summary.update(
        {
            "dataset": str(ds.root),
            "split": split,
            "command": command,
            "options": options or {},
            "table_source": table_source,
            "outputs": [RESULTS_FILE, JOURNAL_FILE, "per_target.csv", "summary.json", "table.txt"],
        }
    )
    table_text = format_table(summary)
    from .outputs import atomic_write_text

    atomic_write_text(out_dir / "table.txt", table_text + "\n")
    if plots and rows:
        summary["outputs"] += make_plots(out_dir, rows, summary, selection, tables, geometry, gallery)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=1, default=_json_default) + "\n")
    summary["table_text"] = table_text
    return summary


def _stops_the_run(e: Exception) -> bool:
    """Errors that are not one target's: a search-size guard (the same options for every target)."""
    from .cli import SearchTooLarge

    return isinstance(e, SearchTooLarge)


def _failed_rows(selection: Selection, failed: dict) -> list[dict]:
    return [
        {"scene_id": t.scene_id, "im_id": t.im_id, "inst": t.inst, "obj_id": t.obj_id, "failure": failed[t.key]}
        for t in selection.targets
        if t.key in failed
    ]


def _space_details(space, table: Table, target: Target) -> dict:
    """Whether the ground truth lies inside the searched region (diagnostic only, never used by the search)."""
    out: dict = {}
    try:
        out["n_candidates"] = int(len(space))
        _, x, y, _ = decompose_on_table(table, target.R_gt, target.t_gt_m)
        (x0, x1), (y0, y1) = space.x_range_m, space.y_range_m
        out["gt_in_region"] = bool(x0 <= x <= x1 and y0 <= y <= y1)
        out["region_m"] = [[x0, x1], [y0, y1]]
    except (AttributeError, TypeError):
        pass
    return out


# ----------------------------------------------------------------------------- errors and metrics


class GeometryCache:
    """Model vertices/faces (metres) per object, and the subsampled points for ADD(-S)."""

    def __init__(self, model_paths: dict[int, Path], max_points: int = pose_error.DEFAULT_MAX_POINTS):
        self.model_paths = model_paths
        self.max_points = max_points
        self._cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def get(self, obj_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(vertices_m (N, 3), faces (F, 3), ADD-S points_m (<= max_points, 3))."""
        if obj_id not in self._cache:
            from .mesh import load_mesh

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
    cell = probe.get("score")
    return {
        "gt_cell_score": cell,
        "margin": d.score - cell if cell is not None else None,
        "est_points": sil.get("points"),
        "est_edge_share": sil.get("edge_share"),
    }


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
]


def write_per_target(path: Path, rows: list[dict], failed: Sequence[dict] = ()) -> None:
    """per_target.csv: errors in mm / degrees, table-frame poses in metres / degrees; then the failed
    targets, their ids and `failure` (the reason) only. Written atomically."""
    import csv
    import io

    columns = [*_PER_TARGET_COLUMNS, "failure"]
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(columns)
    for r in [*rows, *failed]:
        w.writerow(["" if r.get(c) is None else (f"{r[c]:.10g}" if isinstance(r[c], float) else r[c]) for c in columns])
    from .outputs import atomic_write_text

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
        "mean_runtime_s_per_target": pooled.get("mean_time_s"),
    }
    occ = occlusion_accuracy(rows)
    if occ is not None:
        summary["occlusion"] = occ
    by_label = label_metrics(rows)
    if by_label:
        summary["by_label"] = by_label
    return summary


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
        misses = p.get("misses") or {}
        if any(misses.values()):
            notes.append(
                f"Misses (>= 2 cm): {misses.get('score miss', 0)} score misses (the answer outscores the ground "
                f"truth's cell), {misses.get('search miss', 0)} search misses (the truth's cell scores higher)."
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
    return "\n".join(lines + notes)


# ----------------------------------------------------------------------------- plots


def silhouette(camera: Camera, vertices_m: np.ndarray, faces: np.ndarray, R: np.ndarray, t_m: np.ndarray) -> np.ndarray:
    """Bool (H, W) mask of the model's projection (every face filled; occlusion by other objects ignored)."""
    from PIL import Image, ImageDraw

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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made = []
    by_obj: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_obj[r["obj_id"]].append(r)
    names = {int(k): v["name"] for k, v in summary["objects"].items()}

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
    fig.savefig(out_dir / "adds_curve.png", dpi=110)
    plt.close(fig)
    made.append("adds_curve.png")

    occ = summary.get("occlusion")
    if occ is not None:
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
        fig.savefig(out_dir / "occlusion.png", dpi=110)
        plt.close(fig)
        made.append("occlusion.png")

    lighting = (summary.get("by_label") or {}).get("lighting")
    if lighting:
        _lighting_plot(out_dir / "lighting.png", lighting, plt)
        made.append("lighting.png")

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
    fig.savefig(out_dir / "errors.png", dpi=110)
    plt.close(fig)
    made.append("errors.png")

    if gallery > 0:
        made.append(_gallery(out_dir / "gallery.png", rows, names, selection, geometry, gallery, plt))
    return made


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

    from .image import load_rgb

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


# ----------------------------------------------------------------------------- command line


def _ids(values: list[str] | None, flag: str) -> list[int] | None:
    """ "3,4,8,9" or "3 4 8 9" -> [3, 4, 8, 9]."""
    if not values:
        return None
    out = []
    for v in values:
        for part in str(v).split(","):
            if part.strip():
                try:
                    out.append(int(part))
                except ValueError:
                    raise PerchError(f"{flag} takes integer ids like 3,4,8,9, got {part!r}") from None
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `python -m perch_warp eval` (method and search options are the CLI's shared ones)."""
    from .cli import add_method_arguments, add_search_arguments

    d = parser.add_argument_group("dataset")
    d.add_argument("--dataset", required=True, type=Path, help="BOP dataset folder (models/, SPLIT/SCENE/...)")
    d.add_argument("--split", default="test", help="split folder (default: test)")
    d.add_argument("--scenes", nargs="+", metavar="ID", help="scene ids, e.g. 48,49 (default: all)")
    d.add_argument("--objects", nargs="+", metavar="ID", help="object ids, e.g. 3,4,8,9 (default: all with a mesh)")
    d.add_argument("--max-images", type=int, metavar="N", help="only the first N images that have a target")
    d.add_argument("--models", type=Path, metavar="DIR", help="meshes folder (default: dataset_info.json or models/)")
    d.add_argument(
        "--table-source",
        choices=("auto", "w2c", "depth"),
        default="auto",
        help="table frame: cam_R_w2c/cam_t_w2c, else a RANSAC plane fit to depth (auto); or insist on one",
    )
    o = parser.add_argument_group("output")
    o.add_argument("--out", required=True, type=Path, metavar="OUTDIR", help="results folder (resumed if it exists)")
    o.add_argument("--restart", action="store_true", help="discard earlier results in OUTDIR instead of resuming")
    o.add_argument(
        "--gallery", type=int, default=4, metavar="K", help="best and worst K cases in gallery.png (0: none)"
    )
    o.add_argument("--no-plots", action="store_true", help="write no PNG plots")
    add_method_arguments(parser)
    add_search_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """Entry point of `python -m perch_warp eval`; PerchError propagates to the CLI."""
    import shlex

    from .cli import engine_config_from_args, search_space_from_args
    from .outputs import check_output_dir

    check_output_dir(args.out, "--out")  # before anything is read or searched
    objects = _ids(args.objects, "--objects")
    scenes = _ids(args.scenes, "--scenes")
    if args.max_images is not None and args.max_images < 1:
        raise PerchError(f"--max-images must be at least 1, got {args.max_images}")
    config = engine_config_from_args(args)  # validates the method options before any work
    options = {k: v for k, v in sorted(vars(args).items()) if k not in _NOT_SEARCH_OPTIONS and k not in _EVAL_ARGS}

    def space_fn(camera: Camera, table: Table, resting: RestingPose):
        # The region depends on the view and the table only: never on the ground truth.
        return search_space_from_args(args, camera, table)

    def make_estimator(model_paths: dict[int, Path]) -> Estimator:
        return EngineEstimator(model_paths, args.weights, args.device, config)

    command = shlex.join(["python", "-m", "perch_warp", *sys.argv[1:]])
    try:
        summary = evaluate(
            args.dataset,
            args.out,
            make_estimator=make_estimator,
            space_fn=space_fn,
            split=args.split,
            scenes=scenes,
            objects=objects,
            max_images=args.max_images,
            models_dir=args.models,
            table_source=args.table_source,
            options=options,
            restart=args.restart,
            plots=not args.no_plots,
            gallery=args.gallery,
            command=command,
        )
    except KeyboardInterrupt:
        print(
            f"\ninterrupted: finished targets are saved in {args.out / RESULTS_FILE}; "
            "run the same command again to continue",
            file=sys.stderr,
        )
        return 130
    print(summary["table_text"])
    print(f"wrote {', '.join(summary['outputs'])} in {args.out}")
    if summary["n_failed"]:
        print(
            f"perch_warp: {summary['n_failed']} of {summary['n_targets']} targets failed (reasons in "
            f"{args.out / 'per_target.csv'}); the others are evaluated",
            file=sys.stderr,
        )
        return 1
    return 0
