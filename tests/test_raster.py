"""The raster form of kernel #1 (kernels/raster.py) against the BVH form it replaces on the CPU:
the same rays and ray-triangle test, so the same masks and colours; and the closed-mesh test that
decides whether back faces may be skipped."""

import math

import numpy as np
import pytest
from _device import DEVICE

from perch_warp import render
from perch_warp.camera import Camera
from perch_warp.engine import Engine, EngineConfig
from perch_warp.errors import PerchError
from perch_warp.mesh import ObjectMesh
from perch_warp.render import auto_renderer, is_closed_surface, mesh_renderer, project_boxes
from perch_warp.report import renderer_line
from perch_warp.scene import label_texture, look_at_table, striped_cylinder, textured_box
from perch_warp.search_space import SearchSpace
from perch_warp.table import RestingPose, model_to_camera

CAM = Camera(np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]]), 320, 240)
TABLE = look_at_table(0.5, 45.0, 15.0)


@pytest.fixture(scope="module")
def box():
    return textured_box((0.1, 0.06, 0.04), label_texture(np.random.default_rng(3)))


def _open_box(box: ObjectMesh) -> ObjectMesh:
    """The box without its top face (+z, faces 8 and 9): from above one sees its inside, back faces."""
    keep = np.ones(len(box.faces), bool)
    keep[8:10] = False
    return ObjectMesh(box.vertices_m, box.faces[keep], box.uv, box.texture, None, "open box", "m")


def _poses(mesh: ObjectMesh, n: int, seed: int, spread_m: float = 0.12):
    rng = np.random.default_rng(seed)
    rp = RestingPose.upright(mesh.vertices_m)
    return model_to_camera(
        TABLE, rp, rng.uniform(-spread_m, spread_m, n), rng.uniform(-spread_m, spread_m, n), rng.uniform(0, 7, n)
    )


def _both(mesh: ObjectMesh, camera: Camera, R, t, boxes=None):
    """(mask, rgb) of the same batch from the bvh and the raster form."""
    boxes = project_boxes(camera, mesh.hull_points_m(), R, t) if boxes is None else boxes
    out = []
    for method in ("bvh", "raster"):
        b = mesh_renderer(mesh, DEVICE, method).render(camera, R, t, boxes)
        out.append((b.mask.numpy(), b.rgb.numpy()))
    return out


def test_closed_surface_test(box):
    assert is_closed_surface(box.vertices_m, box.faces)  # seams split its vertices, not its surface
    assert not is_closed_surface(box.vertices_m, _open_box(box).faces)
    inward = box.faces[:, ::-1]  # closed, but wound inwards: its back faces are the ones seen
    assert not is_closed_surface(box.vertices_m, inward)
    cyl = striped_cylinder(0.03, 0.08, np.random.default_rng(0))
    assert is_closed_surface(cyl.vertices_m, cyl.faces)
    assert mesh_renderer(box, DEVICE, "raster").cull_back_faces
    assert not mesh_renderer(_open_box(box), DEVICE, "raster").cull_back_faces
    assert not mesh_renderer(box, DEVICE, "bvh").cull_back_faces


@pytest.mark.parametrize("which", ["closed box", "open box", "cylinder"])
def test_raster_equals_bvh_pixel_for_pixel(box, which):
    mesh = {
        "closed box": box,
        "open box": _open_box(box),
        "cylinder": striped_cylinder(0.03, 0.08, np.random.default_rng(1)),
    }[which]
    R, t = _poses(mesh, 40, seed=2)
    (m0, c0), (m1, c1) = _both(mesh, CAM, R, t)
    assert m0.sum() > 10_000  # the poses show the object
    assert np.array_equal(m0, m1)
    hit = m0 > 0
    assert np.array_equal(c0[hit], c1[hit]) and not c1[~hit].any()


def test_open_mesh_needs_its_back_faces(box):
    """Skipping back faces is only allowed on closed meshes: on the open box it would lose the inside
    seen through the missing top (so the raster form must, and does, keep them there)."""
    opened = _open_box(box)
    R, t = _poses(opened, 20, seed=4)
    boxes = project_boxes(CAM, opened.hull_points_m(), R, t)
    (m0, c0), (m1, c1) = _both(opened, CAM, R, t, boxes)
    r = mesh_renderer(opened, DEVICE, "raster")
    r.dmesh.closed_surface = True  # what a wrong closed-mesh test would do
    b = r.render(CAM, R, t, boxes)
    assert np.array_equal(m0, m1) and (b.mask.numpy() != m0).sum() > 100


def test_memory_chunks_give_the_same_image(box, monkeypatch):
    R, t = _poses(box, 12, seed=5)
    boxes = project_boxes(CAM, box.hull_points_m(), R, t)
    whole = mesh_renderer(box, DEVICE, "raster").render(CAM, R, t, boxes)
    monkeypatch.setattr(render, "VERTEX_SLOTS", 2 * len(box.vertices_m) + 1)  # two candidates per chunk
    chunked = mesh_renderer(box, DEVICE, "raster").render(CAM, R, t, boxes)
    assert np.array_equal(whole.mask.numpy(), chunked.mask.numpy())
    assert np.array_equal(whole.rgb.numpy(), chunked.rgb.numpy())


def test_renderer_option(box):
    # auto on the CPU: raster up to RASTER_FACES_PER_PIXEL faces per pixel of the median box.
    assert render.RASTER_FACES_PER_PIXEL == 3
    assert auto_renderer("cpu", 3_072, 1_024) == "raster" and auto_renderer("cpu", 3_073, 1_024) == "bvh"
    with pytest.raises(PerchError, match="bvh or raster"):
        mesh_renderer(box, DEVICE, "opengl")
    with pytest.raises(PerchError, match="--renderer"):
        EngineConfig(renderer="opengl")


def test_engine_scores_equal_for_both_renderers(box, random_weights, monkeypatch):
    rng = np.random.default_rng(6)
    R, t = _poses(box, 1, seed=7, spread_m=0.03)
    image = mesh_renderer(box, DEVICE).render_image(CAM, R[0], t[0])[0]
    image = np.clip(image + rng.normal(0, 0.05, image.shape) + 0.3 * (image == 0), 0, 1)
    image = np.round(image * 255).astype(np.uint8)
    space = SearchSpace((-0.05, 0.05), (-0.05, 0.05), 0.025, (0, 2 * math.pi), math.radians(60))
    rp = RestingPose.upright(box.vertices_m)
    results = {}
    for method in ("bvh", "raster"):
        cfg = EngineConfig(search="exhaustive", refine=False, top_k=len(space), renderer=method)
        results[method] = Engine(box, random_weights, DEVICE, cfg).estimate(image, CAM, TABLE, rp, space)
    a, b = results["bvh"], results["raster"]
    cfg = EngineConfig(search="exhaustive", refine=False)
    auto = Engine(box, random_weights, DEVICE, cfg).estimate(image, CAM, TABLE, rp, space)
    assert auto.info.renderer == "raster" and auto.info.median_box_px > 1_000
    assert renderer_line(auto) == (
        f"renderer: raster (auto on cpu: 12 faces <= 3 x the median candidate box, "
        f"{auto.info.median_box_px:,.0f} px), closed mesh: back faces skipped"
    )
    # A mesh with more faces per pixel than the rule allows gets the BVH form.
    monkeypatch.setattr(render, "RASTER_FACES_PER_PIXEL", 12 / auto.info.median_box_px / 2)
    many = Engine(box, random_weights, DEVICE, cfg).estimate(image, CAM, TABLE, rp, space)
    assert many.info.renderer == "bvh" and not many.info.cull_back_faces
    assert renderer_line(many).startswith("renderer: bvh (auto on cpu: 12 faces > ")
    assert (a.info.renderer, b.info.renderer) == ("bvh", "raster") and b.info.cull_back_faces
    key = {(c.x_m, c.y_m, c.yaw_rad): c.score for c in a.top_k}
    assert len(key) == len(space) and all(key[(c.x_m, c.y_m, c.yaw_rad)] == c.score for c in b.top_k)


def test_ycb_can_raster_equals_bvh(shared):
    """The potted meat can (16,384 faces, closed, texture seams) at random poses of the reference grid."""
    from perch_warp.bench import load_workload

    w = load_workload(shared / "data" / "ycbv", 2, 1, 9, 1.0, 0.01, 0.1)
    x, y, yaw = w.space.candidates()
    pick = np.random.default_rng(0).choice(len(x), 30, replace=False)
    R, t = model_to_camera(w.table, w.resting, x[pick], y[pick], yaw[pick])
    boxes = project_boxes(w.camera, w.mesh.hull_points_m(), R, t)
    keep = boxes[:, 2] * boxes[:, 3] > 0
    assert is_closed_surface(w.mesh.vertices_m, w.mesh.faces)
    (m0, c0), (m1, c1) = _both(w.mesh, w.camera, R[keep], t[keep], boxes[keep])
    assert m0.sum() > 100_000 and np.array_equal(m0, m1)
    hit = m0 > 0
    differ = np.abs(c0[hit] - c1[hit]).max(1) > 0
    # Only a ray through an edge on a texture seam can colour differently (equal distance: the
    # lower face wins in the raster form, the first found in the BVH's); at most a few pixels.
    assert differ.sum() <= 1e-4 * hit.sum()
