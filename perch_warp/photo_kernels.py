"""Kernels of the demo's photographer (photo.py): a shaded, shadowed photo of a whole scene.

This is the "camera" the engine is checked against, so it deliberately differs from
kernel #1: Lambertian + specular lighting from a point light, hard shadows, and the
host adds colour cast, gamma, blur and sensor noise. Each scene mesh is cast in its
own pass (camera frame, metres) and passes are composited by depth.
"""

import warp as wp

from .kernels.render import MeshLook, surface_color


@wp.kernel(enable_backward=False)
def primary_pass(
    mesh: wp.uint64,
    look: MeshLook,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    depth: wp.array2d(dtype=float),
    albedo: wp.array2d(dtype=wp.vec3),
    normal: wp.array2d(dtype=wp.vec3),
    label: wp.array2d(dtype=wp.int32),
    mesh_label: int,
):
    v, u = wp.tid()
    d = wp.normalize(wp.vec3((float(u) - cx) / fx, (float(v) - cy) / fy, 1.0))
    q = wp.mesh_query_ray(mesh, wp.vec3(0.0, 0.0, 0.0), d, depth[v, u])
    if q.result:
        albedo[v, u] = surface_color(look, q.face, q.u, q.v)
        n = wp.normalize(q.normal)
        if wp.dot(n, d) > 0.0:
            n = -n
        normal[v, u] = n
        depth[v, u] = q.t
        label[v, u] = mesh_label


@wp.kernel(enable_backward=False)
def shadow_pass(
    mesh: wp.uint64,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    light: wp.vec3,
    depth: wp.array2d(dtype=float),
    normal: wp.array2d(dtype=wp.vec3),
    lit: wp.array2d(dtype=float),
):
    v, u = wp.tid()
    t = depth[v, u]
    if t >= 1.0e5:
        return
    d = wp.normalize(wp.vec3((float(u) - cx) / fx, (float(v) - cy) / fy, 1.0))
    p = d * t + normal[v, u] * 1.0e-4
    to_light = light - p
    dist = wp.length(to_light)
    q = wp.mesh_query_ray(mesh, p, to_light / dist, dist)
    if q.result:
        lit[v, u] = 0.0
