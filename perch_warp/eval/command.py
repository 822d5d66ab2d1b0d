"""`python -m perch_warp eval`: its options and entry point (see perch_warp.eval)."""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from pathlib import Path

from ..camera import Camera
from ..errors import PerchError
from ..joint import joint_config
from ..options import (
    add_joint_peaks_argument,
    add_method_arguments,
    add_occluders_argument,
    add_search_arguments,
    engine_config_from_args,
    resolve_occluders,
    search_space_from_args,
)
from ..outputs import check_output_dir
from ..resting import DEFAULT_ROLL_STEP_DEG
from ..table import RestingPose, Table
from .journal import NOT_SEARCH_OPTIONS, RESULTS_FILE
from .protocol import EngineEstimator, Estimator, RestSpec, evaluate

# Recorded separately in eval_config.json.
_EVAL_ARGS = {"dataset", "split", "models", "table_source"}


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
    r = parser.add_argument_group("resting pose")
    r.add_argument(
        "--rest",
        choices=("truth", "stable"),
        default="truth",
        help="truth: height, roll and pitch from the ground truth (the thesis's protocol, default); stable: "
        "every stable pose of the mesh searched together, as a user without ground truth",
    )
    r.add_argument(
        "--roll-step",
        type=float,
        default=DEFAULT_ROLL_STEP_DEG,
        help=f"--rest stable: roll step (deg) on a curved side (default: {DEFAULT_ROLL_STEP_DEG:g})",
    )
    d = parser.add_argument_group("distributed (Ray; docs/distributed.md)")
    d.add_argument(
        "--ray",
        nargs="?",
        const="",
        default=None,
        metavar="ADDRESS",
        help="search the targets on Ray workers: one per GPU, or per --ray-cpus-per-worker CPUs; without "
        "ADDRESS a local cluster on this machine, 'auto' the one `ray start` made here, or HOST:PORT",
    )
    d.add_argument("--ray-workers", type=int, metavar="N", help="at most N workers (default: as many as fit)")
    d.add_argument(
        "--ray-cpus-per-worker", type=int, default=1, metavar="N", help="CPU slots (and threads) per worker (1)"
    )
    _add_joint_arguments(parser)
    add_method_arguments(parser)
    add_search_arguments(parser)


def _add_joint_arguments(parser: argparse.ArgumentParser) -> None:
    j = parser.add_argument_group("several objects")
    j.add_argument(
        "--joint",
        action="store_true",
        help="search every image's targets together and make their answers consistent (the joint step: "
        "no two footprints on one table space, no image region explained twice); the summary says, paired "
        "per target, what it changed",
    )
    add_joint_peaks_argument(j, "--joint")
    add_occluders_argument(j, "--joint")


def run(args: argparse.Namespace) -> int:
    """Entry point of `python -m perch_warp eval`; PerchError propagates to the CLI."""

    check_output_dir(args.out, "--out")  # before anything is read or searched
    objects = _ids(args.objects, "--objects")
    scenes = _ids(args.scenes, "--scenes")
    if args.max_images is not None and args.max_images < 1:
        raise PerchError(f"--max-images must be at least 1, got {args.max_images}")
    config = engine_config_from_args(args)  # validates the method options before any work
    if not (math.isfinite(args.roll_step) and 0 < args.roll_step <= 360):
        raise PerchError(f"--roll-step must be in (0, 360] degrees, got {args.roll_step}")
    config = _joint_setup(args, config)
    options = _search_options(args)

    def space_fn(camera: Camera, table: Table, resting: RestingPose):
        # The region depends on the view and the table only: never on the ground truth.
        return search_space_from_args(args, camera, table)

    rest = RestSpec(args.rest, args.roll_step)

    def make_estimator(model_paths: dict[int, Path]) -> Estimator:
        return EngineEstimator(model_paths, args.weights, args.device, config, rest)

    runner = _ray_runner(args, config, rest) if args.ray is not None else None
    if args.joint:
        from .joint import joint_runner  # imports the engine (Warp): only when asked for

        runner = joint_runner(make_estimator, args.occluders)
    command = shlex.join(["python", "-m", "perch_warp", *sys.argv[1:]])
    try:
        summary = evaluate(
            args.dataset,
            args.out,
            make_estimator=None if runner else make_estimator,
            runner=runner,
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
    return _report(summary, args.out)


def _search_options(args: argparse.Namespace) -> dict:
    """The search settings by option name, recorded in eval_config.json and checked on resume."""
    options = {k: v for k, v in sorted(vars(args).items()) if k not in NOT_SEARCH_OPTIONS and k not in _EVAL_ARGS}
    if args.rest == "truth":  # as before --rest existed, so that earlier OUTDIRs still resume
        options.pop("rest")
        options.pop("roll_step")
    if not args.joint:  # likewise for --joint
        options = {k: v for k, v in options.items() if k not in ("joint", "joint_peaks", "occluders")}
    elif args.occluders == "none":  # as before --occluders existed
        options.pop("occluders")
    return options


def _report(summary: dict, out: Path) -> int:
    """Print the summary table and what was written; exit status 1 when a target failed, else 0."""
    print(summary["table_text"])
    print(f"wrote {', '.join(summary['outputs'])} in {out}")
    if summary["n_failed"]:
        print(
            f"perch_warp: {summary['n_failed']} of {summary['n_targets']} targets failed (reasons in "
            f"{out / 'per_target.csv'}); the others are evaluated",
            file=sys.stderr,
        )
        return 1
    return 0


def _joint_setup(args: argparse.Namespace, config):
    """--joint's checks and its EngineConfig (every object's distinct peaks refined); config unchanged without it."""
    resolve_occluders(args, args.joint, "--joint (the other targets' answers hide parts)")
    if not args.joint:
        return config
    if args.joint_peaks < 1:
        raise PerchError(f"--joint-peaks must be at least 1, got {args.joint_peaks}")
    if args.ray is not None:
        raise PerchError("--joint runs without --ray (an image's targets are searched together, in this process)")
    return joint_config(config, args.joint_peaks)


def _ray_runner(args: argparse.Namespace, config, rest: RestSpec):
    """eval --ray's TargetRunner (perch_warp.distributed), its options checked before any work."""
    from ..distributed.cluster import require_ray
    from ..distributed.eval_runner import RayOptions, ray_runner

    require_ray()  # before anything is read: without Ray, say how to install it
    for flag, n in (("--ray-workers", args.ray_workers), ("--ray-cpus-per-worker", args.ray_cpus_per_worker)):
        if n is not None and n < 1:
            raise PerchError(f"{flag} must be at least 1, got {n}")
    ray_options = RayOptions(args.ray or None, args.ray_workers, args.ray_cpus_per_worker)
    return ray_runner(ray_options, args.weights, args.device, config, rest=rest)
