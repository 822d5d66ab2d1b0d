"""Kernel #1: ray-cast candidates' boxes through one `wp.Mesh` (model frame, metres).

Candidates are packed flat: candidate c owns pixels [pix_off[c], pix_off[c+1]) that
cover its image box (x0, y0, w, h) row by row, so boxes of different sizes waste
no threads. Rays are expressed in the model frame (one BVH for all poses).
"""

import warp as wp


@wp.func
def find_candidate(offsets: wp.array(dtype=wp.int32), n: int, i: int) -> int:
    """Index c with offsets[c] <= i < offsets[c+1] (binary search over n candidates)."""
    lo = int(0)  # int(...) makes a mutable (dynamic) Warp variable
    hi = int(n)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if offsets[mid] <= i:
            lo = mid
        else:
            hi = mid
    return lo


@wp.func
def box_pixel(pix_off: wp.array(dtype=wp.int32), box: wp.array(dtype=wp.vec4i), n_cand: int, i: int):
    """Flat pixel i: its candidate c and image pixel (u, v); candidate c owns pixels
    [pix_off[c], pix_off[c+1]) of its box box[c] = (x0, y0, w, h), row by row."""
    c = find_candidate(pix_off, n_cand, i)
    b = box[c]
    local = i - pix_off[c]
    return c, b[0] + local % b[2], b[1] + local // b[2]


@wp.func
def bilinear_taps(uv: wp.vec2, w: int, h: int):
    """The four texels (x0, y0), (x1, y1) of a bilinear lookup at uv in a w x h texture, row 0 at
    v = 0, UVs wrapped (OBJ convention), and the weights fx, fy of x1 and y1."""
    x = (uv[0] - wp.floor(uv[0])) * float(w) - 0.5
    y = (uv[1] - wp.floor(uv[1])) * float(h) - 0.5
    x0f = wp.floor(x)
    y0f = wp.floor(y)
    x0 = (int(x0f) + w) % w
    y0 = (int(y0f) + h) % h
    return x0, y0, (x0 + 1) % w, (y0 + 1) % h, x - x0f, y - y0f


@wp.func
def sample_texture(tex: wp.array2d(dtype=wp.vec3), uv: wp.vec2) -> wp.vec3:
    """Bilinear lookup (bilinear_taps)."""
    x0, y0, x1, y1, fx, fy = bilinear_taps(uv, tex.shape[1], tex.shape[0])
    top = tex[y0, x0] * (1.0 - fx) + tex[y0, x1] * fx
    bot = tex[y1, x0] * (1.0 - fx) + tex[y1, x1] * fx
    return top * (1.0 - fy) + bot * fy


@wp.func
def surface_uv(indices: wp.array(dtype=wp.int32), uvs: wp.array(dtype=wp.vec2), face: int, bu: float, bv: float):
    """Texture coordinates at barycentric (bu, bv) of `face` (Warp's barycentrics weight the
    face's corners as (u, v, 1 - u - v))."""
    w2 = 1.0 - bu - bv
    return uvs[indices[face * 3 + 0]] * bu + uvs[indices[face * 3 + 1]] * bv + uvs[indices[face * 3 + 2]] * w2


@wp.func
def vertex_color(indices: wp.array(dtype=wp.int32), colors: wp.array(dtype=wp.vec3), face: int, bu: float, bv: float):
    """Vertex colour interpolated at barycentric (bu, bv) of `face`."""
    w2 = 1.0 - bu - bv
    return colors[indices[face * 3 + 0]] * bu + colors[indices[face * 3 + 1]] * bv + colors[indices[face * 3 + 2]] * w2


@wp.struct
class MeshLook:
    """A mesh's appearance on the device (model frame): triangle corner indices (3 per face), per
    vertex texture coordinates and a texture (RGB in [0, 1], row 0 at v = 0) when use_texture is 1,
    else per vertex colours. Every kernel that colours a hit takes this one struct."""

    indices: wp.array(dtype=wp.int32)
    uvs: wp.array(dtype=wp.vec2)
    texture: wp.array2d(dtype=wp.vec3)
    colors: wp.array(dtype=wp.vec3)
    use_texture: int
    # Mip-mapped lookups (score term texture=mip, perch_warp/mipmap.py); mip_levels 0: one bilinear
    # lookup in `texture` per pixel, as in the thesis. mip packs the pyramid's levels flat (level 0 =
    # texture), mip_dims[l] = (offset, width, height) of level l; face_texels[f] = face f's unit normal
    # (model frame) and its texels per metre at level 0.
    mip: wp.array(dtype=wp.vec3)
    mip_dims: wp.array(dtype=wp.vec3i)
    face_texels: wp.array(dtype=wp.vec4)
    mip_levels: int


@wp.func
def surface_color(look: MeshLook, face: int, bu: float, bv: float) -> wp.vec3:
    """Unlit colour at barycentric (bu, bv) of `face`: texture lookup or interpolated vertex colour."""
    if look.use_texture != 0:
        return sample_texture(look.texture, surface_uv(look.indices, look.uvs, face, bu, bv))
    return vertex_color(look.indices, look.colors, face, bu, bv)


@wp.func
def sample_level(look: MeshLook, level: int, uv: wp.vec2) -> wp.vec3:
    """sample_texture's bilinear lookup in level `level` of the packed pyramid."""
    d = look.mip_dims[level]
    w = d[1]
    x0, y0, x1, y1, fx, fy = bilinear_taps(uv, w, d[2])
    top = look.mip[d[0] + y0 * w + x0] * (1.0 - fx) + look.mip[d[0] + y0 * w + x1] * fx
    bot = look.mip[d[0] + y1 * w + x0] * (1.0 - fx) + look.mip[d[0] + y1 * w + x1] * fx
    return top * (1.0 - fy) + bot * fy


@wp.func
def texture_lod(look: MeshLook, face: int, depth_m: float, ray_m: wp.vec3, f_px: float) -> float:
    """Mip level (fractional, >= 0) whose texel is as wide as the pixel's footprint on `face`: the
    footprint of a pixel at camera depth depth_m is depth_m / f_px wide facing the ray (f_px the focal
    length in pixels) and covers 1 / cos(incidence) times that area on an inclined face, so its side
    is taken as depth_m / f_px / sqrt(cos) (an isotropic filter of the footprint's area; cos clamped
    at 0.05, so grazing faces are not blurred without limit)."""
    ft = look.face_texels[face]
    cos_i = wp.max(wp.abs(wp.dot(wp.vec3(ft[0], ft[1], ft[2]), wp.normalize(ray_m))), 0.05)
    texels = ft[3] * depth_m / f_px / wp.sqrt(cos_i)
    if texels <= 1.0:
        return 0.0
    return wp.min(wp.log2(texels), float(look.mip_levels - 1))


@wp.func
def sample_mip(look: MeshLook, uv: wp.vec2, lod: float) -> wp.vec3:
    """Trilinear lookup: the two levels around `lod`, blended."""
    l0 = int(wp.floor(lod))
    fr = lod - float(l0)
    a = sample_level(look, l0, uv)
    if fr > 0.0 and l0 + 1 < look.mip_levels:
        return a * (1.0 - fr) + sample_level(look, l0 + 1, uv) * fr
    return a


@wp.func
def srgb_to_linear(c: float) -> float:
    if c <= 0.04045:
        return c / 12.92
    return wp.pow((c + 0.055) / 1.055, 2.4)


@wp.func
def linear_to_srgb(x: float) -> float:
    if x <= 0.0031308:
        return 12.92 * x
    return 1.055 * wp.pow(x, 1.0 / 2.4) - 0.055


@wp.struct
class Shading:
    """Lambert shading of the render (score term shade=s, perch_warp.score_terms): a hit's colour, in
    linear light, times 1 - s + s max(0, n . l), with n the mesh's vertex normals (normals, model frame)
    interpolated at the hit and l the unit direction towards the light (light_m, model frame).
    strength 0: the colour as it is, as in the thesis (normals may then be a placeholder)."""

    normals: wp.array(dtype=wp.vec3)
    light_m: wp.vec3
    strength: float


@wp.func
def light_factor(sh: Shading, indices: wp.array(dtype=wp.int32), face: int, bu: float, bv: float) -> float:
    """What the light makes of a hit at barycentric (bu, bv) of `face` (Shading); 1 when unshaded."""
    if sh.strength == 0.0:
        return 1.0
    n = vertex_color(indices, sh.normals, face, bu, bv)  # the same barycentric blend as a vertex colour
    cos_in = wp.max(wp.dot(wp.normalize(n), sh.light_m), 0.0)
    return 1.0 - sh.strength + sh.strength * cos_in


@wp.func
def exposed(c: float, gain: float) -> float:
    """An sRGB value as a camera exposed `gain` times brighter records it: the light is linear, the
    sensor clips at white."""
    return linear_to_srgb(wp.min(gain * srgb_to_linear(c), 1.0))


@wp.func
def lit(c: wp.vec3, f: float) -> wp.vec3:
    """sRGB colour c with its linear light scaled by f, clipped at white (exposed, per channel); c as it
    is for f = 1, so the unshaded render keeps the thesis's colours bit for bit."""
    if f == 1.0:
        return c
    return wp.vec3(exposed(c[0], f), exposed(c[1], f), exposed(c[2], f))


@wp.struct
class PixelRays:
    """A batch's pixel rays in the model frame: the pinhole intrinsics (pixels) and, per candidate c,
    the camera-to-model rotation rot_c2m[c] and the camera centre origin_m[c] (metres), where
    candidate c's rays start. Every kernel that casts candidates' pixel rays takes this one struct
    and pixel_ray_m, so all of them cast the same rays (the bound's silhouette is the render's)."""

    fx: float
    fy: float
    cx: float
    cy: float
    rot_c2m: wp.array(dtype=wp.mat33)
    origin_m: wp.array(dtype=wp.vec3)


@wp.func
def pixel_ray_m(rays: PixelRays, c: int, u: int, v: int) -> wp.vec3:
    """Direction (model frame) of candidate c's ray through pixel (u, v), from rays.origin_m[c]."""
    return rays.rot_c2m[c] * wp.vec3((float(u) - rays.cx) / rays.fx, (float(v) - rays.cy) / rays.fy, 1.0)


@wp.struct
class RenderedBoxes:
    """Kernel #1's output as kernel #2 reads it: colour rgb (RGB in [0, 1]) and mask (1 on the mesh) per
    flat pixel, candidate c owning pixels [pix_off[c], pix_off[c+1]) of its box box[c] = (x0, y0, w, h),
    row by row (box_pixel)."""

    rgb: wp.array(dtype=wp.vec3)
    mask: wp.array(dtype=wp.uint8)
    box: wp.array(dtype=wp.vec4i)
    pix_off: wp.array(dtype=wp.int32)


@wp.kernel(enable_backward=False)
def render_boxes(
    mesh: wp.uint64,
    look: MeshLook,
    rays: PixelRays,
    box: wp.array(dtype=wp.vec4i),
    pix_off: wp.array(dtype=wp.int32),
    n_cand: int,
    shading: Shading,
    out_rgb: wp.array(dtype=wp.vec3),
    out_mask: wp.array(dtype=wp.uint8),
):
    i = wp.tid()
    c, u, v = box_pixel(pix_off, box, n_cand, i)
    ray = pixel_ray_m(rays, c, u, v)  # its camera-frame z is 1, so q.t is the hit's depth (m)
    q = wp.mesh_query_ray(mesh, rays.origin_m[c], ray, 1.0e6)
    if q.result:
        rgb = wp.vec3()
        if look.mip_levels > 0 and look.use_texture != 0:
            uv = surface_uv(look.indices, look.uvs, q.face, q.u, q.v)
            f_px = wp.sqrt(rays.fx * rays.fy)
            rgb = sample_mip(look, uv, texture_lod(look, q.face, q.t, ray, f_px))
        else:
            rgb = surface_color(look, q.face, q.u, q.v)
        out_rgb[i] = lit(rgb, light_factor(shading, look.indices, q.face, q.u, q.v))
        out_mask[i] = wp.uint8(1)
    else:
        out_rgb[i] = wp.vec3(0.0, 0.0, 0.0)
        out_mask[i] = wp.uint8(0)
