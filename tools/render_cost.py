"""Where does a render's time go? The renderer's kernel against ray-only variants, on the same rays.

    python tools/render_cost.py [--device cpu] [--poses 300] [--seed 0] [--out render_cost.json]

Poses drawn at random from the reference workload's grid (ycbv test scene 2 image 1, potted
meat can, visible table clipped to 1 m, 1 cm / 0.1 rad); their boxes are cast four ways, each
launch timed after a warm-up launch (kernel build), best of --repeat:

- render: kernel #1 in its BVH form (`--renderer bvh`: closest hit, texture lookup, colour and mask);
- closest hit only: the same traversal, writing only the mask;
- any hit: `wp.mesh_query_ray_anyhit` (the silhouette alone, as the bound pass needs);
- closest hit with an oracle max_t: each ray's own hit distance (+0.01 %) as the query's limit,
  the best that carrying a neighbouring pixel's hit distance could do;
- raster: kernel #1's raster form (kernels/raster.py, `--renderer raster`), which must give the same
  mask and, but for texture-seam ties, the same colours.

Also: the fraction of box pixels that the 11x11 windows of on-mask stride-4 feature points read
(the most that rendering only the windows' pixels could save). All kernels must agree on the mask.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp
from perch_warp.kernels.render import PixelRays, box_pixel, pixel_ray_m

from perch_warp.bench import (
    add_frame_arguments,
    add_pose_sample_arguments,
    default_dataset,
    git_commit,
    load_workload,
    sample_grid_poses,
    search_camera,
)
from perch_warp.features import caffe_weights_path
from perch_warp.mesh import ObjectMesh
from perch_warp.render import BvhRenderer, DeviceMesh, RasterRenderer, flat_offsets, project_boxes


@wp.kernel(enable_backward=False)
def closest_hit_only(
    mesh: wp.uint64,
    rays: PixelRays,
    box: wp.array(dtype=wp.vec4i),
    pix_off: wp.array(dtype=wp.int32),
    n_cand: int,
    max_t: wp.array(dtype=float),
    out_t: wp.array(dtype=float),
):
    i = wp.tid()
    c, u, v = box_pixel(pix_off, box, n_cand, i)  # kernel #1's pixels and rays
    q = wp.mesh_query_ray(mesh, rays.origin_m[c], pixel_ray_m(rays, c, u, v), max_t[i])
    out_t[i] = wp.where(q.result, q.t, -1.0)


@wp.kernel(enable_backward=False)
def any_hit(
    mesh: wp.uint64,
    rays: PixelRays,
    box: wp.array(dtype=wp.vec4i),
    pix_off: wp.array(dtype=wp.int32),
    n_cand: int,
    out_mask: wp.array(dtype=wp.uint8),
):
    i = wp.tid()
    c, u, v = box_pixel(pix_off, box, n_cand, i)
    d = pixel_ray_m(rays, c, u, v)
    out_mask[i] = wp.where(wp.mesh_query_ray_anyhit(mesh, rays.origin_m[c], d, 1.0e6), wp.uint8(1), wp.uint8(0))


def window_fraction(mask: np.ndarray, boxes: np.ndarray, pix_off: np.ndarray, ks: int = 11, stride: int = 4) -> float:
    """Share of box pixels inside the ks x ks window of some on-mask feature point (grid u = ks//2 + stride*k)."""
    half = ks // 2
    need = total = 0
    for c, (x0, y0, w, h) in enumerate(boxes.tolist()):
        m = mask[pix_off[c] : pix_off[c + 1]].reshape(h, w).astype(bool)
        us = [u for u in range(x0, x0 + w) if u >= half and (u - half) % stride == 0]
        vs = [v for v in range(y0, y0 + h) if v >= half and (v - half) % stride == 0]
        nd = np.zeros_like(m)
        for v in vs:
            for u in us:
                if m[v - y0, u - x0]:
                    nd[max(0, v - half - y0) : v + half + 1 - y0, max(0, u - half - x0) : u + half + 1 - x0] = True
        need += int(nd.sum())
        total += w * h
    return need / total


def subdivided(mesh: ObjectMesh, times: int) -> ObjectMesh:
    """`mesh` with every face split into 4 at its edge midpoints (UVs, colours alike), `times` times:
    the same surface and appearance with 4^times the faces."""
    import trimesh

    V, F = mesh.vertices_m, mesh.faces
    attrs = {k: a for k, a in (("uv", mesh.uv), ("colors", mesh.vertex_colors)) if a is not None}
    for _ in range(times):
        V, F, attrs = trimesh.remesh.subdivide(V, F, vertex_attributes=attrs)
    return replace(
        mesh,
        vertices_m=np.asarray(V),
        faces=np.asarray(F, np.int32),
        uv=None if mesh.uv is None else np.asarray(attrs["uv"], np.float32),
        vertex_colors=None if mesh.vertex_colors is None else np.asarray(attrs["colors"], np.float32),
    )


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if not (0 < args.image_scale <= 1) or args.subdivide < 0:
        print("render_cost: --image-scale must be in (0, 1] and --subdivide >= 0", file=sys.stderr)
        return 1
    dataset = args.dataset or default_dataset()
    if dataset is None or caffe_weights_path() is None:
        print("render_cost: shared/data/ycbv not found (set PERCH_WARP_SHARED)", file=sys.stderr)
        return 1
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    w = load_workload(dataset, args.scene, args.image, args.obj, 1.0, 0.01, 0.1)
    mesh = subdivided(w.mesh, args.subdivide)
    cam = search_camera(w.camera, args.image_scale)
    hull_m = mesh.hull_points_m()
    R, t, boxes = sample_grid_poses(w, args.poses, args.seed, lambda R, t: project_boxes(cam, hull_m, R, t))
    dmesh = DeviceMesh(mesh, args.device)
    seconds, masks, same_colour = _time_variants(dmesh, cam, R, t, boxes, args)
    mask = masks.pop("render")
    agree = {k: float((m == mask).mean()) for k, m in masks.items()}
    report = {
        "device": args.device,
        "commit": git_commit(),
        "command": " ".join(["python", "tools/render_cost.py", *sys.argv[1:]]),
        "mesh_faces": int(len(mesh.faces)),
        "subdivide": args.subdivide,
        "image_scale": args.image_scale,
        "poses": int(len(boxes)),
        "rays": len(mask),
        "hit_fraction": float((mask > 0).mean()),
        "seconds": seconds,
        "mask_agreement_with_render": agree,
        "raster_back_faces_skipped": RasterRenderer(dmesh).cull_back_faces,
        "raster_same_colour_fraction": same_colour,
        "window_pixel_fraction": window_fraction(mask, boxes, flat_offsets(boxes)),
    }
    _print_report(report, cam)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
    ok = all(v == 1.0 for v in agree.values()) and same_colour >= 0.9999
    return 0 if ok else 1


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_frame_arguments(ap)
    add_pose_sample_arguments(ap)
    ap.add_argument("--device", default="cpu", help="Warp device (default: cpu)")
    ap.add_argument("--repeat", type=int, default=2, help="timed launches per variant, best kept (default 2)")
    ap.add_argument(
        "--image-scale", type=float, default=1.0, help="the photo resized by this factor, as the search's option"
    )
    ap.add_argument(
        "--subdivide",
        type=int,
        default=0,
        help="split every face into 4 this many times (the same surface, 4^N x the faces): how the two "
        "forms of kernel #1 scale with the face count",
    )
    ap.add_argument("--out", type=Path, default=None, help="write the figures here as JSON")
    return ap


def _time_variants(dmesh: DeviceMesh, cam, R: np.ndarray, t: np.ndarray, boxes: np.ndarray, args):
    """Seconds of each variant of kernel #1 over the boxes (best of args.repeat after a warm-up), each
    variant's mask per box pixel (0/1; "render": the BVH render's, the reference) and the share of the
    render's hit pixels the raster form colours the same."""
    renderer = BvhRenderer(dmesh)
    pix_off = flat_offsets(boxes)
    n = int(pix_off[-1])
    with wp.ScopedDevice(args.device):
        common = [
            renderer.wp_mesh.id,
            renderer.pixel_rays(cam, R, t),
            wp.array(boxes, dtype=wp.vec4i),
            wp.array(pix_off, dtype=wp.int32),
            len(boxes),
        ]

        def timed(fn) -> float:
            fn()  # warm-up: builds the kernel
            wp.synchronize_device(args.device)
            best = float("inf")
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                fn()
                wp.synchronize_device(args.device)
                best = min(best, time.perf_counter() - t0)
            return best

        out: dict = {}
        out["render"] = timed(lambda: out.__setitem__("batch", renderer.render(cam, R, t, boxes)))
        bvh_batch = out.pop("batch")
        mask, rgb = bvh_batch.mask.numpy(), bvh_batch.rgb.numpy()
        far = wp.full(n, 1.0e6, dtype=float)
        t_hit = wp.empty(n, dtype=float)
        out["closest_hit_only"] = timed(lambda: wp.launch(closest_hit_only, n, inputs=[*common, far], outputs=[t_hit]))
        th = t_hit.numpy()
        oracle = wp.array(np.where(th > 0, th * 1.0001, 1.0e6).astype(np.float32), dtype=float)
        t_hit2 = wp.empty(n, dtype=float)
        out["closest_hit_oracle_max_t"] = timed(
            lambda: wp.launch(closest_hit_only, n, inputs=[*common, oracle], outputs=[t_hit2])
        )
        m_any = wp.empty(n, dtype=wp.uint8)
        out["any_hit"] = timed(lambda: wp.launch(any_hit, n, inputs=common, outputs=[m_any]))
        raster = RasterRenderer(dmesh)
        out["raster"] = timed(lambda: out.__setitem__("batch", raster.render(cam, R, t, boxes)))
        raster_batch = out.pop("batch")
    masks = {
        "render": mask,
        "closest_hit_only": (th > 0).astype(np.uint8),
        "closest_hit_oracle_max_t": (t_hit2.numpy() > 0).astype(np.uint8),
        "any_hit": m_any.numpy(),
        "raster": raster_batch.mask.numpy(),
    }
    hit = mask > 0
    same_colour = float((raster_batch.rgb.numpy()[hit] == rgb[hit]).all(1).mean())
    seconds = {k: out[k] for k in ("render", "closest_hit_only", "any_hit", "closest_hit_oracle_max_t", "raster")}
    return seconds, masks, same_colour


def _print_report(report: dict, cam) -> None:
    n = report["rays"]
    print(
        f"{report['poses']} poses, {n:,} rays ({100 * report['hit_fraction']:.1f} % hit), "
        f"mesh {report['mesh_faces']} faces, image {cam.width}x{cam.height}, {report['device']}, "
        f"commit {report['commit']}"
    )
    for k, s in report["seconds"].items():
        print(f"  {k:<26}{s:8.3f} s  {n / s / 1e6:6.2f} M rays/s  ({s / report['seconds']['render']:.2f}x render)")
    print(f"  mask agreement with render: {report['mask_agreement_with_render']}")
    print(f"  raster: same colour as render on {100 * report['raster_same_colour_fraction']:.4f} % of hit pixels")
    print(f"  box pixels read by on-mask feature windows: {100 * report['window_pixel_fraction']:.1f} %")


if __name__ == "__main__":
    sys.exit(main())
