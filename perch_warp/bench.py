"""`python -m perch_warp bench`: the reference speed workload, a ray-casting microbenchmark and its CPU peer.

Reference workload (fixed, so figures from different commits and devices compare):
the real YCB-Video frame ycbv test scene 2 image 1, the potted meat can (obj 9), the
visible table clipped to 1 m x 1 m (`perch_warp eval`'s region: nothing derived from
the ground truth), x/y step 1 cm, yaw step 0.1 rad over the full circle; height,
roll and pitch from the ground truth as in `perch_warp eval`. `--warmup` untimed runs
(default one, reported apart), then `--repeat` timed runs.

Microbenchmark: one ray per pixel of the whole (search-scale) image through the
engine's own `wp.Mesh`, for a few poses of the search grid that the image sees fully
(kernels/raycast_bench.py), writing only the hit parameter. Peer: Open3D's
`RaycastingScene` (Embree, CPU) casting the same rays at the same mesh; both must
agree on hit/miss for at least 99.9 % of the rays.

Writes OUT/bench.json and OUT/bench.txt (the table, also printed).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import bop, pose_error
from .camera import Camera
from .errors import PerchError
from .image import load_rgb
from .kernels.raycast_bench import MISS  # the hit parameter written where a ray meets nothing
from .mesh import ObjectMesh, load_mesh
from .render import camera_in_model, pixel_rays  # the rays of kernel #1
from .search_space import SearchSpace
from .table import RestingPose, Table, decompose_on_table

STAGES = (
    "photo_features",
    "rarity",
    "candidates",
    "bound",
    "render",
    "features_score",
    "transfer",
    "reduction",
    "refine",
    "total",
)
AGREEMENT_MIN = 0.999  # hit/miss agreement the microbenchmark and its peer must reach
PEER_NOT_INSTALLED = "peer skipped: open3d not installed (pip install open3d)"
PEER_NAME = "Open3D RaycastingScene (Embree, CPU)"
ENV_COMMIT = "PERCH_WARP_COMMIT"  # names the commit where the checkout's .git cannot


# ----------------------------------------------------------------------------- the workload


@dataclass
class Workload:
    """One frame, one object instance and its search region (table frame, metres)."""

    label: str
    image: np.ndarray  # uint8 (H, W, 3), full size
    camera: Camera  # full-size intrinsics
    table: Table
    table_source: str
    mesh: ObjectMesh
    resting: RestingPose  # height, roll, pitch from the ground truth (thesis protocol)
    R_gt: np.ndarray  # model -> camera
    t_gt_m: np.ndarray
    truth_xy_yaw: tuple[float, float, float]  # table frame: metres, metres, radians
    space: SearchSpace
    adds_points_m: np.ndarray  # model points for ADD-S, subsampled as `perch_warp eval` does


def default_dataset() -> Path | None:
    """shared/data/ycbv when the shared folder is found (see perch_warp.paths)."""
    from .paths import shared_file

    return shared_file("data", "ycbv")


def load_workload(
    dataset: str | Path,
    scene_id: int,
    im_id: int,
    obj_id: int,
    clip_m: float,
    xy_step_m: float,
    yaw_step_rad: float,
    split: str = "test",
) -> Workload:
    """The frame, its table, the object's first instance and the visible-table region, as `perch_warp eval` has them."""
    for name, v, unit in (("--clip", clip_m, "m"), ("--xy-step", xy_step_m, "m"), ("--yaw-step", yaw_step_rad, "rad")):
        if not (math.isfinite(v) and v > 0):
            raise PerchError(f"{name} must be a positive number of {unit}, got {v}")
    ds = bop.open_dataset(dataset, split)
    selection = bop.select_targets(ds, scenes=[scene_id], objects=[obj_id])
    im = next((i for i in selection.images if i.im_id == im_id), None)
    if im is None:
        raise PerchError(f"object {obj_id} is not in scene {scene_id} image {im_id} of {ds.split_dir}")
    target = im.targets[0]  # the first instance, as listed in scene_gt.json
    table, how = bop.TableCache(how="auto").get(im)
    resting, gx, gy, gyaw = decompose_on_table(table, target.R_gt, target.t_gt_m)
    # The default region of `perch_warp eval`: the visible table, clipped (never the ground truth).
    space = SearchSpace.visible_table(im.camera, table, xy_step_m=xy_step_m, yaw_step_rad=yaw_step_rad, clip_m=clip_m)
    len(space)  # validates the ranges
    mesh = load_mesh(selection.model_paths[obj_id])
    return Workload(
        label=f"{ds.root.name} {split} scene {scene_id} image {im_id}, {ds.object_name(obj_id)} (obj {obj_id})",
        image=load_rgb(im.rgb),
        camera=im.camera,
        table=table,
        table_source=how,
        mesh=mesh,
        resting=resting,
        R_gt=target.R_gt,
        t_gt_m=target.t_gt_m,
        truth_xy_yaw=(gx, gy, gyaw),
        space=space,
        adds_points_m=pose_error.subsample_points(mesh.vertices_m),
    )


# ----------------------------------------------------------------------------- environment


def git_commit(repo: Path | None = None) -> str:
    """`git rev-parse --short HEAD` of the checkout holding this package; 'unknown' outside one.

    $PERCH_WARP_COMMIT overrides it: a copy of a working tree on another machine (a lent
    GPU, say) may carry a `.git` that is not the code's, and its figures must name the right commit.
    """
    if os.environ.get(ENV_COMMIT):
        return os.environ[ENV_COMMIT]
    repo = repo or Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


def git_dirty(repo: Path | None = None) -> bool | None:
    """Whether the checkout has uncommitted changes (figures then belong to no commit); None outside one
    or when $PERCH_WARP_COMMIT names the commit."""
    if os.environ.get(ENV_COMMIT):
        return None
    repo = repo or Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=repo,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return bool(out.stdout.strip()) if out.returncode == 0 else None


def command_line() -> str:
    """This process's command line as typed (`python -m perch_warp ...` for the module entry point)."""
    argv = list(sys.argv)
    head = ["python", "-m", "perch_warp"] if argv and argv[0].endswith("__main__.py") else argv[:1]
    return shlex.join(head + argv[1:])


def device_name(device: str) -> str:
    """A readable name: the GPU's, or the CPU model with its logical CPU count."""
    import warp as wp

    d = wp.get_device(device)
    if d.is_cuda:
        return f"{device}: {d.name}"
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"cpu: {model} ({os.cpu_count()} logical CPUs)"


def host_peak_mib() -> float:
    """Peak resident memory of this process so far (ru_maxrss), MiB."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1 << 20) if sys.platform == "darwin" else rss / 1024.0  # bytes on macOS, KiB on Linux


def device_peak_mib(device: str) -> tuple[float | None, str]:
    """High-water mark of Warp's CUDA memory pool on `device` (MiB) and what it is; None with the reason otherwise."""
    import warp as wp

    d = wp.get_device(device)
    if not d.is_cuda:
        return None, "n/a on the CPU"
    try:
        if not wp.is_mempool_enabled(d):
            return None, "n/a: Warp's CUDA memory pool is disabled on this device"
        return wp.get_mempool_used_mem_high(d) / (1 << 20), "peak of Warp's CUDA memory pool (since the process began)"
    except (RuntimeError, ValueError) as e:
        return None, f"n/a: {e}"


# ----------------------------------------------------------------------------- the search


def time_search(engine, w: Workload, repeat: int, warmup: int = 1) -> dict:
    """`warmup` untimed estimates, then `repeat` timed ones: per-stage times (s), throughput, the pose and its ADD-S."""
    from .pose_error import add_s

    if repeat < 1 or warmup < 0:
        raise PerchError(f"--repeat must be at least 1 and --warmup at least 0, got {repeat} and {warmup}")
    args = (w.image, w.camera, w.table, w.resting, w.space)
    warm = None
    for _ in range(warmup):
        t0 = time.perf_counter()
        res = engine.estimate(*args)
        warm = {"wall_s": time.perf_counter() - t0, "timings_s": dict(res.timings_s)}
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = engine.estimate(*args)
        runs.append({"wall_s": time.perf_counter() - t0, "timings_s": dict(res.timings_s)})
    stages = [s for s in STAGES if any(s in r["timings_s"] for r in runs)]
    mean = {s: float(np.mean([r["timings_s"].get(s, 0.0) for r in runs])) for s in stages}
    best = {s: float(np.min([r["timings_s"].get(s, 0.0) for r in runs])) for s in stages}
    wall = float(np.mean([r["wall_s"] for r in runs]))
    evaluated = int(res.info["evaluated"])
    rays = int(res.info["rays"])
    b = res.best
    gx, gy, gyaw = w.truth_xy_yaw
    return {
        "space": w.space.describe(),
        "candidates_in_space": int(res.n_candidates),
        "candidates_evaluated": evaluated,
        "candidates_scored": int(res.n_scored),
        "rays_per_run": rays,
        "batches": int(res.info["batches"]),
        "threads": int(res.info.get("threads", 1)),
        "repeat": repeat,
        "warmup": warm,
        "runs": runs,
        "timings_s_mean": mean,
        "timings_s_min": best,
        "wall_s_mean": wall,
        "candidates_per_s": evaluated / wall if wall > 0 else None,
        # Per thread where several CPU threads render at once (the render stage is then their summed time).
        "rays_per_s_render": rays / mean["render"] if mean.get("render", 0.0) > 0 else None,
        "refine": res.info.get("refine"),
        "pose": {"x_m": b.x_m, "y_m": b.y_m, "yaw_rad": b.yaw_rad, "score": b.score},
        "truth": {"x_m": gx, "y_m": gy, "yaw_rad": gyaw},
        "adds_m": add_s(b.T_m2c[:3, :3], b.T_m2c[:3, 3], w.R_gt, w.t_gt_m, w.adds_points_m),
    }


# ----------------------------------------------------------------------------- microbenchmark and peer


def search_camera(camera: Camera, image_scale: float) -> Camera:
    """The camera the engine searches with (the photo resized by `image_scale`)."""
    return camera if image_scale == 1.0 else camera.scaled(image_scale)


def sample_grid_poses(
    w: Workload, n: int, seed: int, boxes_of: Callable[[np.ndarray, np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to n poses of the workload's grid drawn at random (`seed`), those with an empty image box
    left out: R_m2c (m, 3, 3), t_m2c_m (m, 3) metres (model to camera) and their pixel boxes (m, 4)
    (x0, y0, w, h) from boxes_of(R_m2c, t_m2c_m). The poses tools/ time kernels on."""
    from .table import model_to_camera

    R, t = model_to_camera(w.table, w.resting, *w.space.sample(n, seed))
    boxes = boxes_of(R, t)
    keep = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
    return R[keep], t[keep], boxes[keep]


def poses_in_view(
    w: Workload, camera: Camera, n: int, max_tried: int = 4096
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n poses of the search grid whose whole projection lies in the image, drawn with a fixed seed.

    Returns (R_m2c (n, 3, 3), t_m2c_m (n, 3), (x_m, y_m, yaw_rad) (n, 3)). At most
    `max_tried` grid poses are projected, so this stays cheap for large grids. Drawn at
    random (seed 0) rather than evenly spaced: with yaw varying fastest, an even spacing
    can alias onto one yaw.
    """
    from .render import project_boxes
    from .table import model_to_camera

    if n < 1:
        raise PerchError(f"--ray-poses must be at least 1, got {n}")
    rng = np.random.default_rng(0)
    x, y, yaw = w.space.candidates()
    pick = np.sort(rng.choice(len(x), size=min(len(x), max_tried), replace=False))
    R, t = model_to_camera(w.table, w.resting, x[pick], y[pick], yaw[pick])
    box = project_boxes(camera, w.mesh.hull_points_m(), R, t)
    inside = (
        (box[:, 2] > 0)
        & (box[:, 0] >= 0)
        & (box[:, 1] >= 0)
        & (box[:, 0] + box[:, 2] <= camera.width)
        & (box[:, 1] + box[:, 3] <= camera.height)
    )
    ok = np.flatnonzero(inside)
    if len(ok) == 0:
        raise PerchError(f"no pose of the search grid lies wholly in the image ({w.space.describe()})")
    sel = np.sort(rng.choice(ok, size=min(n, len(ok)), replace=False))
    return R[sel], t[sel], np.stack([x[pick][sel], y[pick][sel], yaw[pick][sel]], -1)


def _timed_loop(step, min_time_s: float) -> tuple[int, float, float]:
    """Call `step()` (which must finish its work) until min_time_s has passed, at least once.

    Returns (calls, wall seconds, process CPU seconds): CPU / wall is how many cores were busy.
    """
    calls = 0
    c0, t0 = time.process_time(), time.perf_counter()
    while True:
        step()
        calls += 1
        wall = time.perf_counter() - t0
        if wall >= min_time_s:
            return calls, wall, time.process_time() - c0


def warp_raycast(
    wp_mesh,
    camera: Camera,
    R_m2c: np.ndarray,
    t_m2c_m: np.ndarray,
    device: str,
    min_time_s: float = 0.0,
) -> tuple[np.ndarray, dict]:
    """Hit parameters (P, H, W) of one ray per pixel and pose through `wp_mesh` (MISS where none), and timings.

    The ray direction's camera-frame z is 1, so a hit parameter is the hit's depth (m).
    One warm-up launch (kernel build or load) is timed apart.
    """
    import warp as wp

    from .kernels.raycast_bench import cast_depth

    rays = pixel_rays(camera, np.asarray(R_m2c, np.float64), np.asarray(t_m2c_m, np.float64), device)
    P = len(R_m2c)
    with wp.ScopedDevice(device):
        out = wp.empty((P, camera.height, camera.width), dtype=float)

    def launch() -> None:
        wp.launch(
            cast_depth,
            dim=(P, camera.height, camera.width),
            inputs=[wp_mesh.id, rays],
            outputs=[out],
            device=device,
        )
        wp.synchronize_device(device)

    t0 = time.perf_counter()
    launch()
    warmup_s = time.perf_counter() - t0
    calls, wall, cpu = _timed_loop(launch, min_time_s)
    n = P * camera.width * camera.height
    return out.numpy(), {
        "rays_per_launch": n,
        "launches": calls,
        "seconds": wall,
        "rays_per_s": n * calls / wall,
        "warmup_s": warmup_s,
        "cpu_busy_cores": cpu / wall if not device.startswith("cuda") else None,
    }


def open3d_raycast(
    mesh: ObjectMesh, camera: Camera, R_m2c: np.ndarray, t_m2c_m: np.ndarray, min_time_s: float = 0.0
) -> tuple[np.ndarray, dict]:
    """The same rays as `warp_raycast` through Open3D's RaycastingScene (Embree, all CPU threads).

    Returns hit parameters (P, H, W) in the same unit (MISS where none) and timings; rays
    are built beforehand (Warp builds its own in the kernel). Raises ImportError without open3d.
    """
    import open3d as o3d

    R_c2m, origin_m = camera_in_model(np.asarray(R_m2c, np.float64), np.asarray(t_m2c_m, np.float64))
    P, H, W = len(R_c2m), camera.height, camera.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    d_c = np.stack(
        [
            (u - np.float32(camera.cx)) / np.float32(camera.fx),
            (v - np.float32(camera.cy)) / np.float32(camera.fy),
            np.ones_like(u),
        ],
        -1,
    )
    rays = np.empty((P, H, W, 6), dtype=np.float32)
    rays[..., :3] = origin_m[:, None, None, :]
    rays[..., 3:] = np.einsum("pij,hwj->phwi", R_c2m, d_c)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices_m.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
    )
    rays_t = o3d.core.Tensor(rays)
    box: dict = {}

    def cast() -> None:
        box["t"] = scene.cast_rays(rays_t)["t_hit"]

    t0 = time.perf_counter()
    cast()  # builds Embree's BVH on first use
    warmup_s = time.perf_counter() - t0
    calls, wall, cpu = _timed_loop(cast, min_time_s)
    t = box["t"].numpy().reshape(P, H, W)
    n = P * H * W
    return np.where(np.isfinite(t), t, MISS).astype(np.float32), {
        "name": PEER_NAME,
        "version": o3d.__version__,
        "rays_per_launch": n,
        "launches": calls,
        "seconds": wall,
        "rays_per_s": n * calls / wall,
        "warmup_s": warmup_s,
        "cpu_busy_cores": cpu / wall,
    }


def compare_hits(t_a: np.ndarray, t_b: np.ndarray) -> dict:
    """Hit/miss agreement of two hit-parameter arrays (MISS = no hit), and depth differences where both hit (m)."""
    hit_a, hit_b = t_a != MISS, t_b != MISS
    both = hit_a & hit_b
    diff = np.abs(t_a[both].astype(np.float64) - t_b[both].astype(np.float64))
    agreement = float(np.mean(hit_a == hit_b)) if t_a.size else float("nan")
    return {
        "rays": int(t_a.size),
        "agreement": agreement,
        "agreement_ok": bool(agreement >= AGREEMENT_MIN),
        "disagreeing_rays": int(np.count_nonzero(hit_a != hit_b)),
        "depth_abs_diff_median_m": float(np.median(diff)) if diff.size else None,
        "depth_abs_diff_max_m": float(diff.max()) if diff.size else None,
    }


def peer_unavailable_reason() -> str | None:
    """None when open3d imports; else the line the report prints instead of the peer."""
    try:
        import open3d  # noqa: F401
    except ModuleNotFoundError:
        return PEER_NOT_INSTALLED
    except ImportError as e:  # installed but broken (e.g. a missing system library)
        return f"peer skipped: open3d cannot be imported ({' '.join(str(e).split())})"
    return None


def time_raycast(engine, w: Workload, image_scale: float, n_poses: int, min_time_s: float, peer: bool) -> dict:
    """The microbenchmark on the engine's mesh and, unless skipped, its Open3D peer on the same rays."""
    camera = search_camera(w.camera, image_scale)
    R, t, xyyaw = poses_in_view(w, camera, n_poses)
    t_warp, warp_stats = warp_raycast(engine.renderer.wp_mesh, camera, R, t, engine.device, min_time_s)
    out = {
        "image": [camera.width, camera.height],
        "poses": len(R),
        "poses_xy_yaw": xyyaw.tolist(),
        "hit_fraction": float(np.mean(t_warp != MISS)),
        "warp": warp_stats,
    }
    reason = "peer skipped: --no-peer" if not peer else peer_unavailable_reason()
    if reason is not None:
        out["peer"] = {"skipped": reason}
        return out
    t_peer, peer_stats = open3d_raycast(w.mesh, camera, R, t, min_time_s)
    peer_stats.update(compare_hits(t_warp, t_peer))
    peer_stats["warp_over_peer"] = warp_stats["rays_per_s"] / peer_stats["rays_per_s"]
    out["peer"] = peer_stats
    return out


# ----------------------------------------------------------------------------- report


def _rate(v: float | None, unit: str) -> str:
    if v is None:
        return "-"
    for scale, prefix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= scale:
            return f"{v / scale:.3g} {prefix}{unit}"
    return f"{v:.3g} {unit}"


def format_report(r: dict) -> str:
    """bench.txt: the figures of `r` (bench.json's content) as a readable table."""
    s = r["search"]
    gx, gy = s["truth"]["x_m"], s["truth"]["y_m"]
    p = s["pose"]
    dirty = {True: " (with uncommitted changes)", False: "", None: ""}[r.get("git_dirty")]
    lines = [
        "perch_warp bench",
        f"device        {r['device_name']}",
        f"commit        {r['commit']}{dirty}",
        f"command       {r['command']}",
        f"warp          {r['warp_version']}, weights: {r['weights']}",
        f"workload      {r['workload']} (table: {r['table_source']})",
        f"search        {r['settings']['search']}, image scale {r['settings']['image_scale']:g} "
        f"({r['search_image'][0]}x{r['search_image'][1]} px)",
        f"renderer      {r['settings'].get('renderer', 'bvh')}"
        + (" (back faces skipped: closed mesh)" if r["settings"].get("cull_back_faces") else ""),
        f"conv1         {r['settings'].get('conv', 'warp')}",
        f"space         {s['space']}",
        f"setup         {r['setup_s']:.2f} s (engine: mesh upload, kernel build; not timed below)",
        f"warm-up run   {s['warmup']['wall_s']:.3f} s (excluded from the figures below)"
        if s["warmup"]
        else "warm-up run   none (--warmup 0: the kernels were built at setup)",
        "",
        f"{'stage':<16}{'mean s':>11}{'min s':>11}{'share':>8}   ({s['repeat']} timed run{'s' * (s['repeat'] > 1)})",
    ]
    threads = s.get("threads", 1)
    stage_times = {k: v for k, v in s["timings_s_mean"].items() if k != "total"}
    # With several threads the stages overlap: shares are of their summed (CPU) time, not of the wall time.
    tot = sum(stage_times.values()) if threads > 1 else s["timings_s_mean"].get("total", 0.0)
    for stage, v in s["timings_s_mean"].items():
        share = f"{100 * v / tot:7.1f}%" if tot > 0 and stage != "total" else ""
        lines.append(f"{stage:<16}{v:>11.4f}{s['timings_s_min'][stage]:>11.4f}{share:>8}")
    lines.append(f"{'wall (estimate)':<16}{s['wall_s_mean']:>11.4f}")
    if threads > 1:
        lines.append(
            f"              {threads} CPU threads score batches at once: render, features_score, reduction and "
            "transfer are CPU seconds summed over them (shares of the stages' sum); total is wall time"
        )
    lines += [
        "",
        f"candidates    {s['candidates_in_space']} in the space, {s['candidates_evaluated']} evaluated, "
        f"{s['candidates_scored']} scored",
        f"throughput    {_rate(s['candidates_per_s'], 'candidates/s')} (evaluated / wall), "
        f"{_rate(s['rays_per_s_render'], 'rays/s')} (rays / render stage{', per thread' if threads > 1 else ''})",
        f"rays          {s['rays_per_run']:,} pixels ray-cast per run, {s['batches']} batch(es)",
    ]
    ref = s.get("refine")
    if ref:
        lines.append(
            f"refinement    cell of the best grid pose at {ref['step_xy_m'] * 1000:.3g} mm / {ref['step_yaw_deg']:.3g} "
            f"deg: {ref['evaluated']:,} of {ref['candidates']:,} poses scored, {ref['rays']:,} rays (not in the "
            f"figures above), score {ref['score_gain']:+.4f}"
            + (f"; {len(ref['peaks'])} peaks refined" if ref.get("peaks") else "")
        )
    m = r["memory"]
    dev = (
        f"{m['device_peak_mib']:.1f} MiB ({m['device_note']})" if m["device_peak_mib"] is not None else m["device_note"]
    )
    lines.append(f"memory        host peak {m['host_peak_mib']:.1f} MiB (ru_maxrss), device {dev}")
    lines.append(
        f"pose found    x {p['x_m']:+.4f} m, y {p['y_m']:+.4f} m, yaw {math.degrees(p['yaw_rad']):.1f} deg "
        f"(truth x {gx:+.4f} m, y {gy:+.4f} m, yaw {math.degrees(s['truth']['yaw_rad']):.1f} deg); "
        f"ADD-S {s['adds_m'] * 100:.2f} cm"
    )
    rc = r["raycast"]
    wst = rc["warp"]
    lines += [
        "",
        f"ray casting   one ray per pixel, {rc['poses']} poses in view, {rc['image'][0]}x{rc['image'][1]} px each, "
        f"{100 * rc['hit_fraction']:.1f} % of rays hit",
        f"  warp        {_rate(wst['rays_per_s'], 'rays/s')} on {r['device']} ({wst['launches']} launches of "
        f"{wst['rays_per_launch']:,} rays in {wst['seconds']:.3f} s; warm-up {wst['warmup_s']:.3f} s"
        + (f"; {wst['cpu_busy_cores']:.2f} cores busy)" if wst.get("cpu_busy_cores") is not None else ")"),
    ]
    peer = rc["peer"]
    if "skipped" in peer:
        lines.append(f"  {peer['skipped']}")
    else:
        ok = "ok" if peer["agreement_ok"] else f"FAILED: below {100 * AGREEMENT_MIN:g} %"
        med = peer["depth_abs_diff_median_m"]
        lines += [
            f"  open3d      {_rate(peer['rays_per_s'], 'rays/s')} ({peer['name']} {peer['version']}, "
            f"{peer['launches']} calls in {peer['seconds']:.3f} s; {peer['cpu_busy_cores']:.2f} cores busy)",
            f"  warp/open3d {peer['warp_over_peer']:.3g}x",
            f"  agreement   hit/miss equal on {100 * peer['agreement']:.3f} % of {peer['rays']:,} rays "
            f"({peer['disagreeing_rays']} differ; {ok})"
            + (
                f"; depth |diff| median {med:.2e} m, max {peer['depth_abs_diff_max_m']:.2e} m"
                if med is not None
                else ""
            ),
        ]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- command line


def add_frame_arguments(parser) -> None:
    """--dataset/--scene/--image/--obj: the reference frame and object, shared with tools/."""
    parser.add_argument("--dataset", type=Path, default=None, help="BOP dataset folder (default: shared/data/ycbv)")
    parser.add_argument("--scene", type=int, default=2, help="scene id (default: 2)")
    parser.add_argument("--image", type=int, default=1, help="image id (default: 1)")
    parser.add_argument("--obj", type=int, default=9, help="object id; its first instance in the image (default: 9)")


def add_pose_sample_arguments(parser) -> None:
    """--poses/--seed: the random grid poses of sample_grid_poses, shared with tools/."""
    parser.add_argument("--poses", type=int, default=300, help="random poses of the reference grid (default 300)")
    parser.add_argument("--seed", type=int, default=0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `python -m perch_warp bench` (defaults: the reference workload)."""
    w = parser.add_argument_group("workload (default: the reference workload)")
    add_frame_arguments(w)
    w.add_argument("--split", default="test", help="split folder (default: test)")
    w.add_argument("--clip", type=float, default=1.0, help="visible table clipped to a square this wide, m (default 1)")
    w.add_argument("--xy-step", type=float, default=0.01, help="x/y step, m (default: 0.01)")
    w.add_argument("--yaw-step", type=float, default=0.1, help="yaw step over the full circle, rad (default: 0.1)")
    m = parser.add_argument_group("engine")
    m.add_argument("--device", default=None, help="Warp device: cpu | cuda:0 (default: a GPU if Warp sees one)")
    m.add_argument("--weights", default="caffe", help="conv1 weights: caffe | torchvision | auto | FILE.npz")
    m.add_argument("--search", default="exhaustive", choices=["exhaustive", "pruned", "coarse-to-fine"])
    m.add_argument(
        "--renderer",
        default="auto",
        choices=["auto", "bvh", "raster"],
        help="kernel #1's form: bvh or raster (same images); auto: by faces per box pixel on the CPU, bvh on a GPU",
    )
    m.add_argument(
        "--conv",
        default="auto",
        choices=["auto", "warp", "torch"],
        help="kernel #2's conv1: warp or torch (same values up to rounding); auto: torch on the CPU, warp on a GPU",
    )
    m.add_argument("--image-scale", type=float, default=1.0, help="search on the photo resized by this factor")
    m.add_argument("--cpu-threads", type=int, default=None, help="CPU device: batches at once (default: one per core)")
    m.add_argument(
        "--refine",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="search the best grid pose's cell at 2 mm / 1 deg, as the CLI does (default: on)",
    )
    m.add_argument(
        "--refine-peaks", type=int, default=1, help="refine this many distinct grid peaks, as the CLI (default: 1)"
    )
    b = parser.add_argument_group("benchmark")
    b.add_argument("--repeat", type=int, default=1, help="timed runs after the warm-up runs (default: 1)")
    b.add_argument(
        "--warmup",
        type=int,
        default=1,
        help="untimed runs first (default: 1; 0 for long CPU runs: setup builds kernels)",
    )
    b.add_argument("--ray-poses", type=int, default=8, help="poses in the ray-casting microbenchmark (default: 8)")
    b.add_argument(
        "--min-time", type=float, default=1.0, help="microbenchmark: repeat launches for at least this many s (1)"
    )
    b.add_argument("--no-peer", action="store_true", help="skip the Open3D peer of the microbenchmark")
    b.add_argument("--out", type=Path, default=Path("perch_warp_bench"), help="folder for bench.json and bench.txt")


def run(args: argparse.Namespace) -> int:
    """Entry point of `python -m perch_warp bench`; PerchError propagates to the CLI."""
    import warp as wp

    from .engine import Engine, EngineConfig, default_device
    from .features import load_feature_weights

    dataset = args.dataset or default_dataset()
    if dataset is None:
        raise PerchError("no --dataset given and shared/data/ycbv not found (set PERCH_WARP_SHARED)")
    if args.repeat < 1 or args.ray_poses < 1 or args.warmup < 0:
        raise PerchError(
            f"--repeat and --ray-poses must be at least 1 and --warmup at least 0, "
            f"got {args.repeat}, {args.ray_poses} and {args.warmup}"
        )
    if not (math.isfinite(args.min_time) and args.min_time >= 0):
        raise PerchError(f"--min-time must be a non-negative number of seconds, got {args.min_time}")
    # validates before any work
    config = EngineConfig(
        search=args.search,
        image_scale=args.image_scale,
        cpu_threads=args.cpu_threads,
        refine=args.refine,
        refine_peaks=args.refine_peaks,
        renderer=args.renderer,
        conv=args.conv,
    )
    w = load_workload(dataset, args.scene, args.image, args.obj, args.clip, args.xy_step, args.yaw_step, args.split)
    weights = load_feature_weights(args.weights)
    device = args.device or default_device()
    engine = Engine(w.mesh, weights, device, config)
    threads = engine.cpu_threads()
    on = f"{device}" + (f" ({threads} CPU threads)" if threads > 1 else "")
    print(f"bench: {w.label}; {w.space.describe()} on {on}", file=sys.stderr, flush=True)
    search = time_search(engine, w, args.repeat, args.warmup)
    host_peak = host_peak_mib()  # before the microbenchmark and peer, so it is the search's
    dev_peak, dev_note = device_peak_mib(device)
    raycast = time_raycast(engine, w, args.image_scale, args.ray_poses, args.min_time, peer=not args.no_peer)
    cam = search_camera(w.camera, args.image_scale)
    report = {
        "device": device,
        "device_name": device_name(device),
        "commit": git_commit(),
        "git_dirty": git_dirty(),
        "command": command_line(),
        "warp_version": wp.__version__,
        "weights": weights.source,
        "workload": w.label,
        "table_source": w.table_source,
        "settings": {
            "dataset": str(Path(dataset).resolve()),
            "split": args.split,
            "scene": args.scene,
            "image": args.image,
            "obj": args.obj,
            "clip_m": args.clip,
            "xy_step_m": args.xy_step,
            "yaw_step_rad": args.yaw_step,
            "search": args.search,
            "refine": args.refine,
            "refine_peaks": args.refine_peaks,
            "renderer": engine.renderer.method,
            "renderer_option": args.renderer,
            "cull_back_faces": engine.renderer.cull_back_faces,
            "conv": engine.scorer.conv,
            "conv_option": args.conv,
            "image_scale": args.image_scale,
            "cpu_threads": threads,
            "stride_px": config.stride,
            "alpha": config.alpha,
            "clusters": config.clusters,
        },
        "search_image": [cam.width, cam.height],
        "setup_s": engine.setup_s,
        "search": search,
        "memory": {"host_peak_mib": host_peak, "device_peak_mib": dev_peak, "device_note": dev_note},
        "raycast": raycast,
    }
    text = format_report(report)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench.json").write_text(json.dumps(report, indent=1) + "\n")
    (out / "bench.txt").write_text(text + "\n")
    print(text)
    print(f"wrote {out / 'bench.json'} and {out / 'bench.txt'}", file=sys.stderr)
    return 0
