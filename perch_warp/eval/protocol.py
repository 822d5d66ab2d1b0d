"""The evaluation loop over targets (`evaluate`) and the estimator adapter around `Engine`."""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_erosion
from tqdm import tqdm

from .. import bop, pose_error
from ..bop import ImageInfo, Selection, TableCache, Target, select_targets
from ..camera import Camera
from ..errors import PerchError
from ..image import load_rgb
from ..mesh import load_mesh as load_mesh_file
from ..options import SearchTooLarge
from ..outputs import atomic_write, atomic_write_text, check_output_dir, folder_lock, remove_stale_temporaries
from ..resting import DEFAULT_ROLL_STEP_DEG, stable_rests
from ..search_space import SearchSpace
from ..table import RestingPose, Table, decompose_on_table
from .journal import (
    JOURNAL_FILE,
    RESULTS_FILE,
    Done,
    append_failure,
    append_journal,
    check_config,
    json_default,
    load_state,
    repair_journal,
    write_results,
)
from .metrics import GeometryCache, compute_errors, format_table, summarize, write_per_target
from .plots import heatmap_path, make_plots

# ----------------------------------------------------------------------------- estimator


@dataclass
class Estimate:
    """A model -> camera pose (metres) with the searcher's score and free-form details."""

    R_m2c: np.ndarray
    t_m2c_m: np.ndarray
    score: float
    details: dict = field(default_factory=dict)
    # Seconds of the call spent on diagnostics (the ground truth's cell, the answer's silhouette), which
    # the per-target runtime leaves out.
    diagnostics_s: float = 0.0
    # The best score over yaw per table cell (perch_warp.score_map.ScoreMap), saved under HEATMAP_DIR
    # for the worst targets' heat maps; None: not given.
    heatmap: object = None


@dataclass(frozen=True)
class RestSpec:
    """Which resting poses a target's search runs over (`eval --rest`): "truth", the ground truth's
    height, roll and pitch (the thesis's protocol), or "stable", every stable pose of the mesh
    (perch_warp.resting), a curved side's roll about the object's own axis every `roll_step_deg`."""

    mode: str = "truth"
    roll_step_deg: float = DEFAULT_ROLL_STEP_DEG


#: (target, image_rgb uint8 HxWx3, camera, table, resting, space) -> Estimate
Estimator = Callable[[Target, np.ndarray, Camera, Table, RestingPose, object], Estimate]
#: (camera, table, resting) -> search space (must not look at the ground-truth x, y, yaw)
SpaceFn = Callable[[Camera, Table, RestingPose], object]


class EngineEstimator:
    """The real search: one `Engine` per object, built on first use (outside the timed call).

    `weights` (already loaded) and `load_mesh(obj_id)` replace reading `weights_spec` and the mesh files
    here: Ray workers get both from the driver (perch_warp.distributed)."""

    def __init__(
        self,
        model_paths: dict[int, Path],
        weights_spec: str = "auto",
        device: str | None = None,
        config=None,
        rest: RestSpec = RestSpec(),
        *,
        weights=None,
        load_mesh: Callable[[int], object] | None = None,
    ):
        self.model_paths = model_paths
        self.weights_spec = weights_spec
        self.device = device
        self.config = config  # EngineConfig, None: its defaults
        # The ground truth's resting pose (the thesis's protocol), or every stable pose of the mesh searched
        # together, as a user without ground truth has them.
        self.rest = rest
        self._weights = weights
        self.load_mesh = load_mesh or (lambda obj_id: load_mesh_file(self.model_paths[obj_id]))
        self._engines: dict[int, object] = {}
        self._rests: dict[int, list] = {}

    def prepare(self, obj_id: int) -> None:
        if obj_id in self._engines:
            return
        # Imported on first use: Warp and torch take seconds to import, and other estimators (tests, tools) never
        # need them.
        from ..engine import Engine
        from ..features import load_feature_weights

        if self._weights is None:
            self._weights = load_feature_weights(self.weights_spec)
        mesh = self.load_mesh(obj_id)
        self._engines[obj_id] = Engine(mesh, self._weights, self.device, self.config)
        if self.rest.mode == "stable":
            self._rests[obj_id] = stable_rests(mesh.vertices_m, mesh.faces, self.rest.roll_step_deg)

    def engine(self, obj_id: int):
        """The object's Engine, built on first use."""
        self.prepare(obj_id)
        return self._engines[obj_id]

    def searched(self, target: Target, resting: RestingPose):
        """What the target's search runs over: its ground truth's resting pose, or the mesh's stable ones."""
        return self._rests[target.obj_id] if self.rest.mode == "stable" else resting

    @staticmethod
    def probe(target: Target, table: Table, resting: RestingPose) -> dict:
        """Engine.estimate's diagnostics arguments: the ground truth's cell, scored after the search on
        the same photo. Under --rest stable it is scored under the truth's own resting pose, so a "search
        miss" there also means that pose is not among the stable ones searched."""
        _, xg, yg, yawg = decompose_on_table(table, target.R_gt, target.t_gt_m)
        return {"probe": (xg, yg, yawg), "probe_resting": resting}

    def __call__(self, target: Target, image_rgb, camera, table, resting, space) -> Estimate:
        self.prepare(target.obj_id)
        engine = self._engines[target.obj_id]
        searched = self.searched(target, resting)
        res = engine.estimate(
            image_rgb, camera, table, searched, space, progress=False, **self.probe(target, table, resting)
        )
        return self.estimate_of(engine, res, camera, res.best)

    def estimate_of(self, engine, res, camera: Camera, answer) -> Estimate:
        """The Estimate of `answer` (a Candidate: the search's best, or the joint step's choice) with the
        search's details (Result res) and the answer's silhouette."""
        T = np.asarray(answer.T_m2c, dtype=np.float64)
        details = {
            "n_candidates": int(res.n_candidates),
            "n_evaluated": res.info.evaluated,  # scored: fewer when pruned
            "timings_s": {k: float(v) for k, v in res.timings.items()},
            "device": res.device,
            "top_k": [{"x_m": c.x_m, "y_m": c.y_m, "yaw_rad": c.yaw_rad, "score": c.score} for c in res.top_k],
        }
        if "refine" in res.info.extra:  # where the refinement started (the grid's best) and how far it went
            details["refine"] = res.info.extra["refine"]
        details["probe"] = res.info.extra["probe"]
        if res.resting is not None:
            won = answer.rest or res.resting.label
            details["rest"] = won
            details["rest_z_m"] = next(r.pose.z_m for r in res.resting.rests if r.label == won)
        details["confidence"] = res.confidence.to_dict()
        t = time.perf_counter()
        details["silhouette"] = silhouette_stats(engine, camera, T)
        diagnostics_s = res.timings["probe"] + time.perf_counter() - t
        return Estimate(T[:3, :3], T[:3, 3], float(answer.score), details, diagnostics_s, res.heatmap)


def silhouette_stats(engine, camera: Camera, T_m2c: np.ndarray) -> dict:
    """A pose's silhouette on the engine's feature grid: its feature points (window centres on the
    rendered mask, inside the photo) and the share of them at the edge (whose window is not wholly on
    the mask: those compared with windows composited with the photo)."""
    _, mask = engine.render(camera, T_m2c)
    ks, s = engine.weights.kernel_size, engine.config.stride
    half = ks // 2
    inner = binary_erosion(mask, np.ones((ks, ks), bool), border_value=0)
    centres = np.zeros_like(mask)
    centres[half : camera.height - half : s, half : camera.width - half : s] = True
    n = int((mask & centres).sum())
    edge = int((mask & centres & ~inner).sum())
    return {"points": n, "edge_share": edge / n if n else float("nan")}


def visible_table_space(
    xy_step_m: float = 0.01, yaw_step_rad: float = math.radians(5.0), clip_m: float = 1.0
) -> SpaceFn:
    """The default region: the table the image sees, clipped to clip_m x clip_m (no ground truth used)."""

    def space_fn(camera: Camera, table: Table, resting: RestingPose):
        return SearchSpace.visible_table(camera, table, xy_step_m=xy_step_m, yaw_step_rad=yaw_step_rad, clip_m=clip_m)

    return space_fn


# ----------------------------------------------------------------------------- resume state


# ----------------------------------------------------------------------------- the run


def evaluate(
    dataset_dir: str | Path,
    out_dir: str | Path,
    *,
    make_estimator: Callable[[dict[int, Path]], Estimator] | None = None,
    space_fn: SpaceFn,
    runner: TargetRunner | None = None,
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
    its search region. `runner` instead runs the targets elsewhere (perch_warp.distributed's Ray
    workers) and returns their outcomes; this process alone writes the outputs either way. `options` (JSON)
    are the search settings, recorded in eval_config.json and checked on resume.
    """

    if (make_estimator is None) == (runner is None):
        raise ValueError("evaluate needs make_estimator (serial) or runner, not both")
    runner = runner or serial_runner(make_estimator)
    out_dir = check_output_dir(out_dir, "--out")
    ds = bop.open_dataset(dataset_dir, split, models_dir)
    selection = select_targets(ds, scenes, objects, max_images, table_source)
    if not selection.targets:
        raise PerchError(f"no targets: no instance of objects {sorted(objects or [])} with a mesh in {ds.split_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    with folder_lock(out_dir, "OUTDIR"):
        return _evaluate_locked(
            ds, selection, out_dir, runner, space_fn, split, table_source, options, restart, progress,
            plots, gallery, max_points, command, dataset_dir,
        )  # fmt: skip


def _evaluate_locked(
    ds, selection, out_dir, runner, space_fn, split, table_source, options, restart, progress, plots,
    gallery, max_points, command, dataset_dir,
) -> dict:  # fmt: skip
    """`evaluate` once OUTDIR is locked: the state, the loop over targets and the outputs."""
    config = {
        "dataset": str(Path(dataset_dir).resolve()),
        "split": split,
        "table_source": table_source,
        "options": options or {},
    }
    check_config(out_dir, config, restart)
    # A run killed mid-write (kill -9, power loss) leaves its temporary; the lock says no writer is alive.
    stale = remove_stale_temporaries(out_dir)
    if stale:
        names = ", ".join(t.name for t in stale)
        print(
            f"note: removed {len(stale)} temporary file(s) an interrupted run left in {out_dir}: {names}",
            file=sys.stderr,
        )
    repair_journal(out_dir)
    done, foreign, failed = load_state(out_dir, selection)
    tables = TableCache(table_source)
    _run_targets(out_dir, selection, done, foreign, failed, tables, runner, space_fn, progress)
    write_results(out_dir, selection, done, foreign)  # canonical order, also when nothing was left to do
    run = {"dataset": str(ds.root), "split": split, "command": command, "options": options or {}}
    run["table_source"] = table_source
    return _write_outputs(out_dir, ds, selection, done, failed, tables, max_points, run, plots, gallery)


#: (targets to run, in order; table frames; search-region function; mesh paths by object id) ->
#: (target, its Done or its failure's one-line reason), in any order, each target exactly once.
Outcome = tuple[Target, "Done | str"]
TargetRunner = Callable[[list[tuple[ImageInfo, Target]], TableCache, SpaceFn, dict[int, Path]], Iterator[Outcome]]


@dataclass
class Job:
    """One target's search inputs, prepared where the journal is written (the driver): the camera of its
    image, the table frame (table -> camera, metres) and how it was found, the resting pose from the
    ground truth (height, roll, pitch) and the search region (which never looks at the ground truth)."""

    target: Target
    camera: Camera
    table: Table
    table_how: str
    resting: RestingPose
    space: object


def prepare_job(im: ImageInfo, target: Target, tables: TableCache, space_fn: SpaceFn) -> Job:
    """The inputs of one target's search; PerchError when the target cannot be evaluated."""
    if target.problem:
        raise PerchError(target.problem)
    table, table_how = tables.get(im)
    resting, _, _, _ = decompose_on_table(table, target.R_gt, target.t_gt_m)
    return Job(target, im.camera, table, table_how, resting, space_fn(im.camera, table, resting))


def run_job(job: Job, image_rgb: np.ndarray, estimator: Estimator) -> Done:
    """One target's search, timed (building the engine and the diagnostics are not part of its time)."""
    prepare = getattr(estimator, "prepare", None)
    if callable(prepare):
        prepare(job.target.obj_id)  # building the engine is not part of the per-target runtime
    t0 = time.perf_counter()
    est = estimator(job.target, image_rgb, job.camera, job.table, job.resting, job.space)
    dt = time.perf_counter() - t0 - est.diagnostics_s
    details = dict(est.details)
    details["table"] = job.table_how
    _add_space_details(details, job.space, job.table, job.target)
    R = np.asarray(est.R_m2c, dtype=np.float64).reshape(3, 3)
    t = np.asarray(est.t_m2c_m, dtype=np.float64).reshape(3)
    return Done(job.target.obj_id, R, t, float(est.score), dt, details, heatmap=est.heatmap)


def failure_reason(e: BaseException) -> str:
    """A target's failure as one line: a PerchError's message, else the exception's type and message."""
    reason = str(e) if isinstance(e, PerchError) else f"{type(e).__name__}: {e}"
    return " ".join(reason.split())


def serial_runner(make_estimator: Callable[[dict[int, Path]], Estimator]) -> TargetRunner:
    """Targets one after another in this process; the estimator is made on the first target that needs it."""

    def run(todo, tables: TableCache, space_fn: SpaceFn, model_paths: dict[int, Path]) -> Iterator[Outcome]:
        state = {"estimator": None, "image_key": None, "image": None}
        for im, target in todo:
            # One bad target must not stop a long evaluation: whatever fails in it (its ground truth, its
            # table, its search) is its failure and the run goes on. Options that would fail every target
            # alike (SearchTooLarge) and interruptions still stop the run.
            try:
                job = prepare_job(im, target, tables, space_fn)
                image = _image(state, im)
                if state["estimator"] is None:
                    state["estimator"] = make_estimator(model_paths)
                yield target, run_job(job, image, state["estimator"])
            except Exception as e:  # noqa: BLE001 - recorded with its reason; see above
                if stops_the_run(e):
                    raise
                yield target, failure_reason(e)

    return run


def _image(state: dict, im: ImageInfo) -> np.ndarray:
    """The image's photo, read once for all its targets (targets come in image order)."""
    if state["image_key"] != (im.scene_id, im.im_id):
        state["image"] = None
        state["image_key"] = (im.scene_id, im.im_id)
        state["image"] = load_rgb(im.rgb)
    if state["image"] is None:
        raise PerchError(f"image {im.rgb} could not be read (see the image's first target)")
    return state["image"]


def _run_targets(out_dir, selection, done, foreign, failed, tables, runner: TargetRunner, space_fn, progress) -> None:
    """Search every target not yet done, journalling each (or its failure) and rewriting results.csv.

    This process alone writes: the runner (serial, or Ray workers) only returns outcomes, so a target is
    recorded once whatever happened to the workers."""
    todo = [(im, t) for im in selection.images for t in im.targets if t.key not in done]
    n_before = len(selection.targets) - len(todo)
    if n_before and todo:
        print(f"resuming: {n_before} of {len(selection.targets)} targets already done in {out_dir}", file=sys.stderr)
    expected = {t.key for _, t in todo}
    bar = tqdm(total=len(todo), unit="target", desc="eval", disable=not progress or not todo, dynamic_ncols=True)
    try:
        for target, outcome in runner(todo, tables, space_fn, selection.model_paths):
            if target.key not in expected:  # a duplicate (or a stranger) is never written
                raise PerchError(f"target {target.key} came back twice or was not asked for: a runner bug")
            expected.discard(target.key)
            if isinstance(outcome, str):
                failed[target.key] = outcome
                append_failure(out_dir, target, outcome)
                print(f"target {target.key} (obj {target.obj_id}) failed: {outcome}", file=sys.stderr)
                bar.update(1)
                continue
            # Journal first: if the rewrite below is interrupted, the journal still has the target.
            append_journal(out_dir, target, outcome)
            if outcome.heatmap is not None:  # after the journal: a lost heat map only loses a picture
                atomic_write(heatmap_path(out_dir, target.key), outcome.heatmap.save)
            done[target.key] = outcome
            failed.pop(target.key, None)
            write_results(out_dir, selection, done, foreign)
            bar.set_postfix_str(f"{target.scene_id}/{target.im_id} obj {target.obj_id} {outcome.time_s:.1f}s")
            bar.update(1)
    finally:
        bar.close()
    if expected:
        raise PerchError(f"{len(expected)} targets got no outcome, e.g. {min(expected)}: a runner bug")


def _write_outputs(out_dir, ds, selection, done, failed, tables, max_points, run: dict, plots, gallery) -> dict:
    """per_target.csv, table.txt, the plots and summary.json from the finished targets; returns the summary."""
    geometry = GeometryCache(selection.model_paths, max_points)
    rows = compute_errors(selection, done, tables, geometry)
    write_per_target(out_dir / "per_target.csv", rows, _failed_rows(selection, failed))
    summary = summarize(rows, ds, selection)
    summary["n_failed"] = len(failed)
    summary["failed"] = [{"key": list(k), "reason": r} for k, r in sorted(failed.items())]
    summary["n_gt_rotations_projected"] = sum(t.gt_projected for t in selection.targets)
    summary["gt_rotation_tolerance"] = bop.GT_ROTATION_TOLERANCE
    summary.update(run)
    summary["outputs"] = [RESULTS_FILE, JOURNAL_FILE, "per_target.csv", "summary.json", "table.txt"]
    table_text = format_table(summary)
    atomic_write_text(out_dir / "table.txt", table_text + "\n")
    if plots and rows:
        summary["outputs"] += make_plots(out_dir, rows, summary, selection, tables, geometry, gallery)
    atomic_write_text(out_dir / "summary.json", json.dumps(summary, indent=1, default=json_default) + "\n")
    summary["table_text"] = table_text
    return summary


def stops_the_run(e: BaseException) -> bool:
    """Errors that are not one target's: a search-size guard (the same options for every target)."""
    return isinstance(e, SearchTooLarge)


def _failed_rows(selection: Selection, failed: dict) -> list[dict]:
    return [
        {"scene_id": t.scene_id, "im_id": t.im_id, "inst": t.inst, "obj_id": t.obj_id, "failure": failed[t.key]}
        for t in selection.targets
        if t.key in failed
    ]


def _add_space_details(details: dict, space, table: Table, target: Target) -> None:
    """Adds the searched grid's size and whether the ground truth lies inside the searched region (a
    diagnostic, never used by the search). An estimator's own count wins: under several resting poses
    it is the grid times the poses, while `space` is one pose's (x, y, yaw) grid."""
    try:
        details.setdefault("n_candidates", int(len(space)))
        _, x, y, _ = decompose_on_table(table, target.R_gt, target.t_gt_m)
        (x0, x1), (y0, y1) = space.x_range_m, space.y_range_m
        details["gt_in_region"] = bool(x0 <= x <= x1 and y0 <= y <= y1)
        details["region_m"] = [[x0, x1], [y0, y1]]
    except (AttributeError, TypeError):
        pass


# ----------------------------------------------------------------------------- errors and metrics


# ----------------------------------------------------------------------------- plots


# ----------------------------------------------------------------------------- command line
