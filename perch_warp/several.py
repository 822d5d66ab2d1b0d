"""The main command with several objects: `python -m perch_warp IMAGE --mesh a.obj --mesh b.obj ...` or
`--models DIR --objects 1 3 9`: each object's search on one photo, the joint step (perch_warp.objects,
perch_warp.joint), one JSON with every object, one overlay with all of them, a heat map per object."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from .errors import PerchError
from .estimate import (
    ObjectSpec,
    check_outputs,
    extent_note,
    load_photo,
    photo_inputs,
    read_truth,
    resolve_rest,
    rest_line,
    rests_for,
    truth_error,
)
from .features import load_feature_weights
from .image import save_png
from .joint import joint_config
from .mesh import load_mesh
from .objects import ObjectAnswer, estimate_objects
from .options import build_engine, engine_config_from_args, search_space_from_args
from .outputs import check_output_file
from .overlay import caption, overlay_rendering
from .report import log, timing_line, write_json_atomic
from .table import Table

# Overlay colours, one per object in order (then repeated).
COLORS = [
    ("magenta", (255, 0, 255)),
    ("cyan", (0, 200, 255)),
    ("orange", (255, 160, 0)),
    ("green", (120, 255, 0)),
    ("red", (255, 60, 60)),
    ("violet", (160, 110, 255)),
]


def run_several(args: argparse.Namespace, objects: list[ObjectSpec]) -> int:
    """The several-object command (module doc); PerchError propagates to the CLI."""
    if args.obj_id is not None:
        raise PerchError("--obj-id names one object; with several, --models DIR --objects ID ... name them")
    if args.truth and any(o.obj_id is None for o in objects):
        raise PerchError("--truth with several objects needs --models DIR --objects ID ... (their ids in --truth)")
    if args.joint_peaks < 1:
        raise PerchError(f"--joint-peaks must be at least 1, got {args.joint_peaks}")
    config = joint_config(engine_config_from_args(args), args.joint_peaks)
    args.rest = resolve_rest(args, ids_known=all(o.obj_id is not None for o in objects))
    check_outputs(args)
    if args.heatmap:
        for n, o in enumerate(objects):
            check_output_file(heatmap_path(args.heatmap, n, o), "--heatmap")
    image_id, camera, table = photo_inputs(args)
    space = search_space_from_args(args, camera, table)
    meshes, truths, restings = _load_objects(args, objects, image_id, table)
    image = load_photo(args, camera)
    weights = load_feature_weights(args.weights)
    engines = [build_engine(args, m, args.quiet or n > 0, config, weights) for n, m in enumerate(meshes)]
    if not args.quiet:
        log(f"search: {space.describe()}" + extent_note(table))
        log(f"objects: {len(objects)}, each with its best {config.refine_peaks} distinct peaks refined")
    searched = [r[0].pose if len(r) == 1 else r for r in restings]
    if not args.quiet and args.occluders == "answers":
        log("occluders: each object searched again with the others' answers hiding what they cover")
    answers, choice = estimate_objects(
        engines, [o.name for o in objects], image, camera, table, searched, space, progress=not args.quiet,
        occluders=args.occluders,
    )  # fmt: skip
    out = {"image": str(args.image), "rest": args.rest, "objects": [], "joint": choice.to_dict()}
    for o, a, mesh, truth, rests in zip(objects, answers, meshes, truths, restings, strict=True):
        out["objects"].append(_report_object(o, a, mesh, truth, rests, args.rest))
    print(joint_line(choice, objects, answers))
    if args.out:
        write_json_atomic(args.out, out)
    if args.overlay:
        _write_overlay(args.overlay, engines, image, camera, objects, answers)
    if args.heatmap:
        _write_heatmaps(args.heatmap, image, camera, table, objects, answers, truths)
    return 0


def _load_objects(args: argparse.Namespace, objects: list[ObjectSpec], image_id: int | None, table: Table):
    """Each object's mesh, ground truth (with --truth; else None) and resting poses to search."""
    meshes, truths, restings = [], [], []
    for o in objects:
        truth, truth_resting = read_truth(args, image_id, table, o.obj_id) if args.truth else (None, None)
        mesh = load_mesh(o.mesh, args.mesh_units, untextured=args.untextured)
        rests = rests_for(args, mesh, truth_resting)
        if not args.quiet:
            log(f"{o.name}: {mesh.source}, units {mesh.units_note}, {len(mesh.faces)} faces; "
                f"resting poses ({args.rest}): {len(rests)}")  # fmt: skip
        meshes.append(mesh)
        truths.append(truth)
        restings.append(rests)
    return meshes, truths, restings


def _report_object(o: ObjectSpec, a: ObjectAnswer, mesh, truth, rests: list, mode: str) -> dict:
    """Print one object's lines; its JSON entry (with the truth's errors where known)."""
    entry = _object_entry(o, a, rests, mode)
    print(_object_line(o, a))
    print("  " + rest_line(_won(a, rests), len(rests), mode))
    print("  " + a.result.confidence.line() + ("" if not a.changed else " (of the object's own best)"))
    print("  " + timing_line(a.result))
    if a.first_pass is not None:
        print("  " + first_pass_line(a))
    if truth is not None:
        print("  ", end="")
        entry["truth"] = truth_error(truth, a.best, mesh.vertices_m)
    return entry


def _won(a: ObjectAnswer, rests: list):
    """The Rest of the joint answer (its candidate's label among several; the only one otherwise)."""
    if a.best.rest is None:
        return rests[0]
    return next(r for r in rests if r.label == a.best.rest)


def _object_entry(o: ObjectSpec, a: ObjectAnswer, rests: list, mode: str) -> dict:
    """One object's JSON: its joint answer as "pose", its own search's result beside it."""
    entry = {"name": o.name, "mesh": o.mesh, "obj_id": o.obj_id, "resting": _won(a, rests).to_dict()}
    entry.update(a.result.to_dict())
    entry["pose"] = a.best.to_dict()
    entry["joint"] = {
        "peak": a.pick,
        "changed": a.changed,
        "own_best": a.result.best.to_dict(),
        "peaks": [c.to_dict() for c in a.peaks],
    }
    if a.first_pass is not None:  # --occluders answers: the second pass's record and the first's answer
        entry["occluders"] = {
            **a.result.info.extra.get("hidden", {}),
            **a.result.info.extra.get("known", {}),
            "first_pass": a.first_pass.best.to_dict(),
        }
    return entry


def _object_line(o: ObjectSpec, a: ObjectAnswer) -> str:
    b = a.best
    moved = f" [joint step: peak {a.pick + 1} of {len(a.peaks)}, own best score {a.result.best.score:.4f}]"
    return (
        f"{o.name}: x = {b.x_m:+.4f} m, y = {b.y_m:+.4f} m, yaw = {math.degrees(b.yaw_rad):.1f} deg (table frame), "
        f"score {b.score:.4f}" + (moved if a.changed else "")
    )


def first_pass_line(a: ObjectAnswer) -> str:
    """Where the first pass (no occluders) put the object, against the answer with the others hiding parts."""
    f, b = a.first_pass.best, a.best
    if not a.second_pass_changed:
        return f"first pass (no occluders): the same pose, score {f.score:.4f}"
    moved_cm = 100.0 * math.hypot(b.x_m - f.x_m, b.y_m - f.y_m)
    return (
        f"first pass (no occluders): x = {f.x_m:+.4f} m, y = {f.y_m:+.4f} m, yaw = {math.degrees(f.yaw_rad):.1f} deg, "
        f"score {f.score:.4f} ({moved_cm:.1f} cm from this answer)"
    )


def joint_line(choice, objects: list[ObjectSpec], answers: list[ObjectAnswer]) -> str:
    """The joint step in one line: how it chose, what it changed, what conflicts remain."""
    changed = [
        o.name + "".join(f" ({why} with {objects[j].name})" for j, why in choice.moved_by(n))
        for n, (o, a) in enumerate(zip(objects, answers, strict=True))
        if a.changed
    ]
    line = f"joint step: {choice.method} over {choice.combinations} combinations; " + (
        "changed " + ", ".join(changed) if changed else "every object keeps its own best"
    )
    for i, j, why in choice.conflicts:
        line += f"; conflict left: {objects[i].name} and {objects[j].name} ({why})"
    return line


def _write_overlay(path, engines, image, camera, objects, answers) -> None:
    """Every object's joint answer over the photo, one colour each."""
    pic = image
    lines = []
    for n, (e, o, a) in enumerate(zip(engines, objects, answers, strict=True)):
        name, color = COLORS[n % len(COLORS)]
        rgb, mask = e.render(camera, a.best.T_m2c)
        pic = overlay_rendering(pic, rgb, mask, color=color)
        b = a.best
        lines.append(
            f"{o.name} ({name}): x {b.x_m:+.3f} m  y {b.y_m:+.3f} m  yaw {math.degrees(b.yaw_rad):.0f} deg"
            f"  score {b.score:.3f}" + ("  (changed by the joint step)" if a.changed else "")
        )
    save_png(path, caption(pic, lines))


def heatmap_path(path: str, n: int, o: ObjectSpec) -> Path:
    """One heat map per object: --heatmap a.png gives a_1_obj_1.png, a_2_obj_3.png, ... (object number, then
    its id or the mesh's stem)."""
    p = Path(path)
    label = f"obj_{o.obj_id}" if o.obj_id is not None else Path(o.mesh).stem
    return p.with_name(f"{p.stem}_{n + 1}_{label}{p.suffix}")


def _write_heatmaps(path, image, camera, table, objects, answers, truths) -> None:
    from .heatmap import write_heatmap  # matplotlib: imported only when a heat map is asked for

    for n, (o, a, truth) in enumerate(zip(objects, answers, truths, strict=True)):
        write_heatmap(heatmap_path(path, n, o), image, camera, table, a.result, None if truth is None else truth[2:4])
