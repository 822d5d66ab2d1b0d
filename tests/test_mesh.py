import numpy as np
import pytest
import trimesh

from perch_warp.errors import PerchError
from perch_warp.mesh import load_mesh
from perch_warp.scene import label_texture, textured_box, write_obj


def test_textured_obj_round_trip_and_unit_detection(tmp_path):
    box = textured_box((0.1, 0.06, 0.04), label_texture(np.random.default_rng(0), 96))
    write_obj(box, tmp_path / "box.obj")
    m = load_mesh(tmp_path / "box.obj")
    assert m.units_note.startswith("m ")
    assert np.allclose(m.vertices_m, box.vertices_m, atol=1e-6)
    assert np.allclose(m.uv, box.uv, atol=1e-6)
    assert np.allclose(m.texture, box.texture, atol=1 / 255)

    mm = type(box)(box.vertices_m * 1000, box.faces, box.uv, box.texture, None, "", "")
    write_obj(mm, tmp_path / "box_mm.obj")
    m2 = load_mesh(tmp_path / "box_mm.obj")
    assert m2.units_note.startswith("mm ") and np.allclose(m2.vertices_m, box.vertices_m, atol=1e-6)
    # A wrong --mesh-units makes a 100 m "object": refused, naming the extent, the unit read and the fix.
    with pytest.raises(PerchError, match=r"100 x 60 x 40 units across, read as m \(given\).*--mesh-units mm"):
        load_mesh(tmp_path / "box_mm.obj", units="m")


def test_ply_with_vertex_colours(tmp_path):
    m = trimesh.creation.box((0.05, 0.05, 0.05))
    m.visual.vertex_colors = np.tile([200, 100, 50, 255], (len(m.vertices), 1))
    m.export(tmp_path / "c.ply")
    got = load_mesh(tmp_path / "c.ply")
    assert got.texture is None and np.allclose(got.vertex_colors, [200 / 255, 100 / 255, 50 / 255])


def test_meshes_without_faces_or_appearance_are_refused(tmp_path):
    (tmp_path / "pts.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(PerchError, match="no faces"):
        load_mesh(tmp_path / "pts.obj")
    (tmp_path / "plain.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(PerchError, match="no texture and no vertex colours"):
        load_mesh(tmp_path / "plain.obj")
    with pytest.raises(PerchError, match="not found"):
        load_mesh(tmp_path / "missing.obj")


def _textured_trimesh(tmp_path):
    from PIL import Image

    box = textured_box((0.1, 0.06, 0.04), label_texture(np.random.default_rng(0), 96))
    img = Image.fromarray((box.texture[::-1] * 255).round().astype(np.uint8))
    img.save(tmp_path / "tex.png")
    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=img, baseColorFactor=[1.0, 1.0, 1.0, 1.0])
    tm = trimesh.Trimesh(
        box.vertices_m, box.faces, visual=trimesh.visual.TextureVisuals(uv=box.uv, material=mat), process=False
    )
    return box, tm


def test_glb_and_ply_with_uvs(tmp_path):
    box, tm = _textured_trimesh(tmp_path)
    tm.export(tmp_path / "b.glb")
    tm.export(tmp_path / "b.ply")
    ply = (tmp_path / "b.ply").read_bytes()
    (tmp_path / "t.ply").write_bytes(ply.replace(b"end_header", b"comment TextureFile tex.png\nend_header", 1))
    for name in ("b.glb", "t.ply"):
        m = load_mesh(tmp_path / name)
        assert np.allclose(m.uv, box.uv, atol=1e-4), name
        assert np.allclose(m.texture, box.texture, atol=1.5 / 255), name
    # UVs without a texture file would silently shade with a placeholder: refused instead.
    with pytest.raises(PerchError, match="TextureFile"):
        load_mesh(tmp_path / "b.ply")


def test_missing_material_or_texture_files_are_refused_and_untextured_is_opt_in(tmp_path):
    box = textured_box((0.1, 0.06, 0.04), label_texture(np.random.default_rng(0), 96))
    write_obj(box, tmp_path / "box.obj")
    (tmp_path / "box.png").unlink()
    with pytest.raises(PerchError, match=r"texture .*box.png \(map_Kd in box.mtl\) is missing"):
        load_mesh(tmp_path / "box.obj")
    (tmp_path / "box.mtl").unlink()
    with pytest.raises(PerchError, match=r"material file .*box.mtl \(mtllib\) is missing"):
        load_mesh(tmp_path / "box.obj", untextured=True)  # a named material is never replaced by grey
    (tmp_path / "plain.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    m = load_mesh(tmp_path / "plain.obj", untextured=True)
    assert np.allclose(m.vertex_colors, 0.5) and "untextured" in m.units_note


def test_degenerate_mesh_names_its_extent(tmp_path):
    (tmp_path / "line.obj").write_text("v 0 0 0\nv 0.1 0 0\nv 0.2 0 0\nf 1 2 3\n")
    with pytest.raises(PerchError, match=r"degenerate: its extent is 0.2 x 0 x 0 units"):
        load_mesh(tmp_path / "line.obj", untextured=True)
    (tmp_path / "tiny.obj").write_text("v 0 0 0\nv 0.0001 0 0\nv 0 0.0001 0\nf 1 2 3\n")
    with pytest.raises(PerchError, match=r"read as m \(auto\): 0.0001 m, outside .*check the mesh file"):
        load_mesh(tmp_path / "tiny.obj", untextured=True)
    (tmp_path / "half.obj").write_text("v 0 0 0\nv 0.5 0 0\nv 0 0.5 0\nf 1 2 3\n")  # 0.5 m, said to be mm
    with pytest.raises(PerchError, match=r"0.5 x 0.5 x 0 units across, read as mm \(given\).*--mesh-units m$"):
        load_mesh(tmp_path / "half.obj", units="mm", untextured=True)
