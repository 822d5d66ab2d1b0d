"""How an object can rest on the table: its stable poses from the mesh (`--rest stable`), upright, or the truth's.

A resting pose is a `table.RestingPose` (R_rest: model -> table rotation at yaw 0, z_m: the model
origin's height in metres, the lowest vertex on the table top z = 0) with a label naming the face down.

Stable poses (`stable_rests`) come from `trimesh.poses.compute_stable_poses` on the mesh's convex hull,
with the hull's centroid as the centre of mass (a solid of uniform density: scanned meshes are rarely
watertight, so their own volume integrals are not trusted) and no sampling noise (sigma 0, one sample):
the list is deterministic. Each stable pose is a hull face the object lands on, with its quasi-static
probability of landing there when dropped at random. Then:

* **Merge only what a yaw relates.** Two resting poses differ by a rotation about the table normal
  exactly when the same model direction points down; the search sweeps yaw anyway, so poses whose
  down directions lie within MERGE_TOL_DEG are one (probabilities summed). Poses that differ by a flip
  (a box on its +z face and on its -z face) stay distinct even when the shape is symmetric: the search
  compares textured appearance, and the two show different faces.
* **Curved sides roll.** A can on its side has no single stable face: its hull offers many narrow
  facets whose down directions all lie (within ROLL_PLANE_TOL_DEG) on one great circle, around the
  can's axis. At least ROLL_MIN_POSES such facets, with every gap between neighbours narrower than
  ROLL_MAX_GAP_DEG (the YCB tomato soup can's widest is 58 deg, where its hull's facets topple), make a
  *curved side*: it is replaced by poses every `roll_step_deg` about that axis
  (the label can face any way), the side's probability shared among them. A box's four sides around
  an axis are only four facets with 90 deg gaps, so boxes never roll.
* **Drop the improbable.** Faces (a curved side counting as one) below `min_probability`
  (MIN_PROBABILITY = 0.02) are dropped: the sugar box standing on its end, as it does in YCB-Video
  scenes, lands there with probability 0.028, so a threshold of 0.05 would lose it; facets of scan
  noise (e.g. a bottom face tilted by 8 deg) land with 0.001-0.011.

The list is sorted by probability (faces before their roll expansion, most probable first; ties
keep trimesh's order), so the pruned search meets the likely poses first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import PerchError
from .table import RestingPose

MIN_PROBABILITY = 0.02
MERGE_TOL_DEG = 5.0
ROLL_PLANE_TOL_DEG = 3.0
ROLL_MIN_POSES = 8
ROLL_MAX_GAP_DEG = 90.0
DEFAULT_ROLL_STEP_DEG = 30.0
REST_MODES = ("stable", "upright", "truth")

_AXES = np.eye(3)
_AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True)
class Rest:
    """A resting pose with what it is: `label` names the face down; `probability` of landing on it
    (NaN when not from the mesh); `down_m`: the model-frame unit vector pointing into the table;
    for a rolled curved side, `axis_m` (model frame) and `roll_deg` about it."""

    pose: RestingPose
    label: str
    probability: float = math.nan
    down_m: np.ndarray | None = None
    axis_m: np.ndarray | None = None
    roll_deg: float | None = None

    def to_dict(self) -> dict:
        out = {
            "label": self.label,
            "z_m": self.pose.z_m,
            "R_rest": self.pose.R_rest.reshape(-1).tolist(),
            "probability": None if math.isnan(self.probability) else self.probability,
        }
        if self.down_m is not None:
            out["down_model"] = [float(v) for v in self.down_m]
        if self.axis_m is not None:
            out["roll_axis_model"] = [float(v) for v in self.axis_m]
            out["roll_deg"] = self.roll_deg
        return out


def direction_name(d: np.ndarray, tol_deg: float = MERGE_TOL_DEG) -> str:
    """'model -z' for a unit vector within tol_deg of a model axis, else its components."""
    i = int(np.argmax(np.abs(d)))
    if abs(d[i]) >= math.cos(math.radians(tol_deg)):
        return f"model {'+' if d[i] > 0 else '-'}{_AXIS_NAMES[i]}"
    return "model (" + ", ".join(f"{v:+.2f}" for v in d) + ")"


def down_to_table(down_m: np.ndarray) -> np.ndarray:
    """The smallest rotation taking the model direction down_m to the table's -z (the identity for
    model -z, so an upright object's stable pose is exactly `RestingPose.upright`'s rotation)."""
    d = np.asarray(down_m, dtype=np.float64)
    d = d / np.linalg.norm(d)
    target = np.array([0.0, 0.0, -1.0])
    c = float(d @ target)
    if c > 1.0 - 1e-12:
        return np.eye(3)
    if c < -1.0 + 1e-12:  # model +z down: half a turn about model x
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(d, target)
    s = np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]]) / s
    return np.eye(3) + s * K + (1 - c) * K @ K


def upright_rest(vertices_m: np.ndarray, lift_m: float = 0.0) -> Rest:
    """Model +z along the table normal, the lowest vertex on the table (plus lift_m): `--rest upright`."""
    return Rest(RestingPose.upright(vertices_m, lift_m=lift_m), "upright (model -z down)", down_m=-_AXES[2])


def truth_rest(pose: RestingPose) -> Rest:
    """The ground truth's height, roll and pitch (the thesis's protocol): `--rest truth`."""
    return Rest(pose, "ground truth's (height, roll, pitch)", down_m=pose.R_rest.T @ np.array([0.0, 0.0, -1.0]))


def _hull(vertices_m: np.ndarray, faces: np.ndarray):
    """The mesh's convex hull as a trimesh, refused (one line) when flat: a flat mesh has no centre of
    mass strictly inside, where trimesh's sampler would never stop."""
    import trimesh

    try:
        with np.errstate(all="ignore"):  # a flat hull's volume integrals divide by zero: refused below
            hull = trimesh.Trimesh(np.asarray(vertices_m, np.float64), np.asarray(faces), process=False).convex_hull
            _ = hull.volume, hull.center_mass
    except Exception as e:  # qhull on degenerate input
        raise PerchError(f"the mesh has no 3-D convex hull ({e}): use --rest upright") from None
    extent = float(np.ptp(hull.vertices, axis=0).max()) if len(hull.vertices) else 0.0
    if extent <= 0 or hull.volume <= 1e-9 * extent**3:
        raise PerchError("the mesh is flat (its convex hull has no volume): no stable poses; use --rest upright")
    com = hull.center_mass
    if not np.all(np.einsum("ij,ij->i", com - hull.triangles_center, hull.face_normals) < 0):
        raise PerchError("the mesh's hull centroid is not strictly inside its hull: use --rest upright")
    return hull, com


def stable_downs(vertices_m: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stable poses of the mesh on a plane: down directions (N, 3; model frame, unit) and probabilities
    (N,), most probable first, straight from trimesh (nothing merged or dropped)."""
    import trimesh

    hull, com = _hull(vertices_m, faces)
    T, probs = trimesh.poses.compute_stable_poses(hull, center_mass=com, sigma=0.0, n_samples=1, seed=0)
    # trimesh's transform puts the contact face's outward normal n along table -z: its third row is -n.
    downs = -np.asarray(T, np.float64)[:, 2, :3]
    return downs / np.linalg.norm(downs, axis=1, keepdims=True), np.asarray(probs, np.float64)


def roll_family(downs: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A curved side among the down directions (see the module doc): (axis (3,), member mask) or None.
    The axis is the plane normal that the most down directions lie on (tried: the normalised cross
    product of every pair at least 10 deg apart), then fitted by least squares to its members."""
    n = len(downs)
    if n < ROLL_MIN_POSES:
        return None
    i, j = np.triu_indices(n, 1)
    cross = np.cross(downs[i], downs[j])
    norm = np.linalg.norm(cross, axis=1)
    ok = norm > math.sin(math.radians(10.0))  # nearly (anti)parallel pairs fix no plane
    if not ok.any():
        return None
    axes = cross[ok] / norm[ok, None]
    tol = math.sin(math.radians(ROLL_PLANE_TOL_DEG))
    counts = (np.abs(axes @ downs.T) < tol).sum(1)
    axis = axes[int(np.argmax(counts))]
    members = np.abs(downs @ axis) < tol
    _, vecs = np.linalg.eigh(downs[members].T @ downs[members])
    axis = vecs[:, 0]  # the normal of the members' best plane through the origin
    axis = axis * np.sign(axis[int(np.argmax(np.abs(axis)))])  # sign fixed: largest component positive
    members = np.abs(downs @ axis) < tol
    if members.sum() < ROLL_MIN_POSES or _largest_gap_deg(downs[members], axis) >= ROLL_MAX_GAP_DEG:
        return None
    return axis, members


def _roll_frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Unit u, v with (u, v, axis) right-handed: roll 0 puts u down; u is the model axis most
    perpendicular to `axis` (first of x, y, z within 0.01 of it: a scanned can's axis is not exactly
    along a model axis), projected; and u's name."""
    dots = np.abs(_AXES @ axis)
    i = int(np.flatnonzero(dots <= dots.min() + 0.01)[0])
    u = _AXES[i] - (_AXES[i] @ axis) * axis
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u), f"model +{_AXIS_NAMES[i]}"


def _largest_gap_deg(downs: np.ndarray, axis: np.ndarray) -> float:
    """The widest angle between neighbouring down directions around `axis` (360 for one)."""
    u, v, _ = _roll_frame(axis)
    ang = np.sort(np.degrees(np.arctan2(downs @ v, downs @ u)) % 360.0)
    gaps = np.diff(np.concatenate([ang, [ang[0] + 360.0]]))
    return float(gaps.max())


def _merge_faces(downs: np.ndarray, probs: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Faces whose down directions lie within MERGE_TOL_DEG of a more probable one's join it (poses
    related by a yaw): [(down, summed probability)], in the order of their most probable member."""
    cos_tol = math.cos(math.radians(MERGE_TOL_DEG))
    kept: list[list] = []
    for d, p in zip(downs, probs, strict=True):
        for k in kept:
            if float(k[0] @ d) >= cos_tol:
                k[1] += float(p)
                break
        else:
            kept.append([d, float(p)])
    return [(d, p) for d, p in kept]


def stable_rests(
    vertices_m: np.ndarray,
    faces: np.ndarray,
    roll_step_deg: float = DEFAULT_ROLL_STEP_DEG,
    min_probability: float = MIN_PROBABILITY,
    lift_m: float = 0.0,
) -> list[Rest]:
    """The mesh's resting poses for `--rest stable` (the module doc says how they are chosen), most
    probable first; a curved side expands into 360 / roll_step_deg rolls. Heights put the lowest
    vertex on the table top (plus lift_m)."""
    if not (math.isfinite(roll_step_deg) and 0 < roll_step_deg <= 360):
        raise PerchError(f"--roll-step must be in (0, 360] degrees, got {roll_step_deg}")
    if not (math.isfinite(min_probability) and 0 <= min_probability < 1):
        raise PerchError(f"the stable-pose probability threshold must be in [0, 1), got {min_probability}")
    downs, probs = stable_downs(vertices_m, faces)
    family = roll_family(downs)
    groups: list[tuple[float, list[Rest]]] = []
    if family is not None:
        axis, members = family
        p_side = float(probs[members].sum())
        groups.append((p_side, _rolls(vertices_m, axis, p_side, roll_step_deg, lift_m)))
        downs, probs = downs[~members], probs[~members]
    for d, p in _merge_faces(downs, probs):
        rest = Rest(RestingPose.upright(vertices_m, down_to_table(d), lift_m), f"{direction_name(d)} down", p, d)
        groups.append((p, [rest]))
    groups = [g for g in groups if g[0] >= min_probability]
    if not groups:
        raise PerchError(f"no stable pose of the mesh has probability >= {min_probability}: use --rest upright")
    groups.sort(key=lambda g: -g[0])  # stable sort: ties keep the order above
    return [r for _, rests in groups for r in rests]


def _rolls(vertices_m: np.ndarray, axis: np.ndarray, p_side: float, step_deg: float, lift_m: float) -> list[Rest]:
    """Resting poses on a curved side: the axis along table x at yaw 0, rolled every step_deg
    (roll 0: the model axis most perpendicular to `axis` points down)."""
    u, v, u_name = _roll_frame(axis)
    n = math.ceil(360.0 / step_deg - 1e-9)  # rolls 0, step, ... below 360 (360 is roll 0 again)
    out = []
    for k in range(n):
        roll = k * step_deg
        d = math.cos(math.radians(roll)) * u + math.sin(math.radians(roll)) * v
        R = np.stack([axis, np.cross(-d, axis), -d])  # rows: table x, y, z in model coordinates
        label = f"side down, roll {roll:g} deg about {direction_name(axis)} ({u_name} down at 0)"
        out.append(Rest(RestingPose.upright(vertices_m, R, lift_m), label, p_side / n, d, axis, roll))
    return out
