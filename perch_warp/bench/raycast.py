"""The ray-casting microbenchmark: one ray per pixel of the whole (search-scale) image through the
engine's own `wp.Mesh` (kernels.py), and its CPU peer, Open3D's RaycastingScene (Embree) on the same rays."""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from ..camera import Camera
from ..mesh import ObjectMesh
from ..render import camera_in_model, pixel_rays  # the rays of kernel #1
from .kernels import MISS, cast_depth  # MISS: the hit parameter written where a ray meets nothing
from .workload import Workload, poses_in_view, search_camera

AGREEMENT_MIN = 0.999  # hit/miss agreement the microbenchmark and its peer must reach
PEER_NOT_INSTALLED = "peer skipped: open3d not installed (pip install open3d)"
PEER_NAME = "Open3D RaycastingScene (Embree, CPU)"


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
    import open3d as o3d  # optional (pip install perch_warp[bench]): the peer is skipped without it

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
    t_warp, warp_stats = warp_raycast(engine.renderer_for("bvh").wp_mesh, camera, R, t, engine.device, min_time_s)
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
