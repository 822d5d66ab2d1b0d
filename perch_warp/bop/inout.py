"""Reading BOP-format datasets and writing BOP results (cf. bop_toolkit_lib's `inout`).

BOP files carry **millimetres** (`cam_t_m2c`, `cam_t_w2c`, model vertices, depth
after `depth_scale`); everything returned here is in **metres** except where a
name ends in `_mm`. Poses are model -> camera (`R_m2c`, `t_m2c_m`).

Layout read (https://github.com/thodan/bop_toolkit/blob/master/docs/bop_datasets_format.md):

    DATASET/models/obj_{id:06d}.obj|.ply (+ models_info.json)
    DATASET/{split}/{scene:06d}/rgb/{im:06d}.png|.jpg
    DATASET/{split}/{scene:06d}/scene_camera.json, scene_gt.json [, scene_gt_info.json, depth/]
    DATASET/camera.json [optional: width, height checked against every image]
    DATASET/dataset_info.json [optional: {"models_dir": "..."}, written by our synthetic generator]

Every malformed input raises `PerchError` naming the file.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..camera import Camera, camera_from_entry, entry_size
from ..errors import PerchError
from ..image import image_header_size
from ..outputs import atomic_write_text

RESULTS_HEADER = "scene_id,im_id,obj_id,score,R,t,time"
MESH_SUFFIXES = (".obj", ".ply")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif")


# ----------------------------------------------------------------------------- JSON files


def read_json(path: str | Path, what: str = "JSON file"):
    """Parse a JSON file; missing or malformed files raise PerchError naming the file."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise PerchError(f"{what} not found: {path}") from None
    except OSError as e:
        raise PerchError(f"cannot read {what} {path}: {e}") from None
    try:
        return json.loads(text)
    except ValueError as e:
        raise PerchError(f"malformed JSON in {path}: {e}") from None


def _id_keyed(data, path: Path) -> dict[int, object]:
    if not isinstance(data, dict):
        raise PerchError(f"{path} must hold a JSON object keyed by integer ids")
    out: dict[int, object] = {}
    for k, v in data.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise PerchError(f"{path}: key {k!r} is not an integer id") from None
    return out


def _floats(value, n: int, path: Path, where: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.size != n or not np.all(np.isfinite(a)):
        raise PerchError(f"{path}: {where} must be {n} finite numbers, got {value!r}")
    return a


def load_scene_camera(path: str | Path) -> dict[int, dict]:
    """`scene_camera.json`: image id -> entry (raw BOP dict, mm), each checked to have a 3x3 `cam_K`."""
    path = Path(path)
    data = _id_keyed(read_json(path, "scene_camera.json"), path)
    for im_id, entry in data.items():
        if not isinstance(entry, dict) or "cam_K" not in entry:
            raise PerchError(f"{path}: entry for image {im_id} has no 'cam_K'")
        _floats(entry["cam_K"], 9, path, f"image {im_id} cam_K")
        for key, n in (("cam_R_w2c", 9), ("cam_t_w2c", 3)):
            if key in entry:
                _floats(entry[key], n, path, f"image {im_id} {key}")
        if "depth_scale" in entry:
            _floats(entry["depth_scale"], 1, path, f"image {im_id} depth_scale")
    return data  # type: ignore[return-value]


# Public BOP annotations store rotations to a few digits, orthonormal only to ~5e-3 per entry. Such a
# rotation is projected onto SO(3) (the nearest rotation, by SVD) when max |R R^T - I| is at most this;
# beyond it (or with det < 0) the instance is no rotation and its target fails with that reason.
GT_ROTATION_TOLERANCE = 2e-2
# Below this max |R R^T - I| a rotation is orthonormal to the file's rounding: not counted as projected.
_GT_ROUNDING = 1e-3


@dataclass(frozen=True)
class GtInstance:
    """One ground-truth object instance: model -> camera, translation in metres.

    `R_m2c` is a rotation (projected onto SO(3) when the file's was near-orthonormal: `projected`);
    `problem` says why the instance cannot be used (its rotation is too far from one), else None.
    """

    obj_id: int
    R_m2c: np.ndarray
    t_m2c_m: np.ndarray
    projected: bool = False
    problem: str | None = None


def gt_rotation(R: np.ndarray) -> tuple[np.ndarray, bool, str | None]:
    """(rotation, projected?, problem) for a ground-truth cam_R_m2c: see GT_ROTATION_TOLERANCE."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    dev = float(np.abs(R @ R.T - np.eye(3)).max())
    if dev > GT_ROTATION_TOLERANCE or np.linalg.det(R) <= 0:
        why = f"max |R R^T - I| = {dev:.3g} > {GT_ROTATION_TOLERANCE:g}" if dev > GT_ROTATION_TOLERANCE else "det < 0"
        return R, False, f"cam_R_m2c is not a rotation ({why})"
    u, _, vt = np.linalg.svd(R)
    return u @ vt, dev > _GT_ROUNDING, None


def load_scene_gt(path: str | Path) -> dict[int, list[GtInstance]]:
    """`scene_gt.json`: image id -> instances in file order (BOP mm converted to metres).

    Malformed entries raise PerchError naming file, image and instance; a rotation too far from one
    does not (one bad instance must not stop an evaluation): it is the instance's `problem`.
    """
    path = Path(path)
    data = _id_keyed(read_json(path, "scene_gt.json"), path)
    out: dict[int, list[GtInstance]] = {}
    for im_id, insts in data.items():
        if not isinstance(insts, list):
            raise PerchError(f"{path}: image {im_id} must map to a list of instances")
        lst = []
        for k, g in enumerate(insts):
            where = f"image {im_id} instance {k}"
            if not isinstance(g, dict) or not {"obj_id", "cam_R_m2c", "cam_t_m2c"} <= set(g):
                raise PerchError(f"{path}: {where} needs obj_id, cam_R_m2c and cam_t_m2c")
            try:
                if isinstance(g["obj_id"], bool) or float(g["obj_id"]) != int(g["obj_id"]):
                    raise ValueError
                obj_id = int(g["obj_id"])
            except (TypeError, ValueError):
                raise PerchError(f"{path}: {where} obj_id {g['obj_id']!r} is not an integer") from None
            R = _floats(g["cam_R_m2c"], 9, path, f"{where} cam_R_m2c").reshape(3, 3)
            t = _floats(g["cam_t_m2c"], 3, path, f"{where} cam_t_m2c (mm)") / 1000.0
            R, projected, problem = gt_rotation(R)
            lst.append(GtInstance(obj_id, R, t, projected, problem and f"{path} {where}: {problem}"))
        out[im_id] = lst
    return out


def truth_instance(path: str | Path, im_id: int | None, obj_id: int | None) -> GtInstance:
    """The ground truth of `obj_id` in image `im_id` (None: the file's only image) from a scene_gt.json,
    read by the same validated reader as `eval`; PerchError naming the file and what is missing."""
    if obj_id is None:
        raise PerchError("--truth needs --obj-id (the object's id in the ground truth)")
    path = Path(path)
    gts = load_scene_gt(path)
    if im_id is None:
        if len(gts) != 1:
            raise PerchError(f"ground truth {path} has {len(gts)} images; say which with --image-id")
        im_id = next(iter(gts))
    if im_id not in gts:
        raise PerchError(f"ground truth {path} has no entry for image id {im_id} (has {sorted(gts)[:10]})")
    inst = [g for g in gts[im_id] if g.obj_id == obj_id]
    if not inst:
        have = sorted({g.obj_id for g in gts[im_id]})
        raise PerchError(f"ground truth {path} has no object {obj_id} in image {im_id} (has objects {have})")
    if inst[0].problem:
        raise PerchError(inst[0].problem)
    return inst[0]


def load_scene_gt_info(path: str | Path) -> dict[int, list[dict]]:
    """`scene_gt_info.json`: image id -> per-instance dicts (we use `visib_fract`, 0..1)."""
    path = Path(path)
    data = _id_keyed(read_json(path, "scene_gt_info.json"), path)
    for im_id, insts in data.items():
        if not isinstance(insts, list) or not all(isinstance(g, dict) for g in insts):
            raise PerchError(f"{path}: image {im_id} must map to a list of objects")
    return data  # type: ignore[return-value]


def load_models_info(path: str | Path) -> dict[int, dict]:
    """`models_info.json`: object id -> info (`diameter` etc. in mm; optional `name`)."""
    path = Path(path)
    data = _id_keyed(read_json(path, "models_info.json"), path)
    for obj_id, info in data.items():
        if not isinstance(info, dict):
            raise PerchError(f"{path}: entry for object {obj_id} must be a JSON object")
    return data  # type: ignore[return-value]


# ----------------------------------------------------------------------------- dataset layout


@dataclass
class Dataset:
    """A BOP dataset on disk: where things are, and the dataset-wide JSON files."""

    root: Path
    split: str
    models_dir: Path
    models_info: dict[int, dict] = field(default_factory=dict)
    camera_info: dict | None = None  # root camera.json (width/height checked against images)

    @property
    def split_dir(self) -> Path:
        return self.root / self.split

    def scene_dir(self, scene_id: int) -> Path:
        return self.split_dir / f"{scene_id:06d}"

    def scene_ids(self) -> list[int]:
        """Scene folders of the split, sorted: only BOP's six-digit names (000002), which `scene_dir` reads back,
        so that a stray folder `2` (or a `²`, which str.isdigit accepts) neither counts scene 2 twice nor breaks."""
        ids = []
        for p in self.split_dir.iterdir():
            name = p.name
            if p.is_dir() and len(name) == 6 and name.isascii() and name.isdigit():
                ids.append(int(name))
        return sorted(ids)

    def model_path(self, obj_id: int) -> Path | None:
        """`models/obj_{id:06d}.obj` or `.ply`, or None when neither exists."""
        for suffix in MESH_SUFFIXES:
            p = self.models_dir / f"obj_{obj_id:06d}{suffix}"
            if p.is_file():
                return p
        return None

    def object_name(self, obj_id: int) -> str:
        """ "004 sugar box" from models_info's `name` "004_sugar_box", else "obj 3"."""
        name = self.models_info.get(obj_id, {}).get("name")
        return str(name).replace("_", " ") if name else f"obj {obj_id}"


def open_dataset(root: str | Path, split: str = "test", models_dir: str | Path | None = None) -> Dataset:
    """Check the dataset's layout and read its dataset-wide files.

    The models folder is `models_dir` when given, else `models_dir` (or `models`) from
    `dataset_info.json` at the root (relative to the root), else `root/models`.
    """
    root = Path(root)
    if not root.is_dir():
        raise PerchError(f"dataset folder not found: {root}")
    split_dir = root / split
    if not split_dir.is_dir():
        have = sorted(p.name for p in root.iterdir() if p.is_dir())
        raise PerchError(f"split folder not found: {split_dir} (the dataset has {have})")
    if models_dir is None:
        info_path = root / "dataset_info.json"
        if info_path.is_file():
            info = read_json(info_path, "dataset_info.json")
            rel = info.get("models_dir", info.get("models")) if isinstance(info, dict) else None
            if rel is not None:
                if not isinstance(rel, str):
                    raise PerchError(f"{info_path}: 'models_dir' must be a path string, got {rel!r}")
                models_dir = root / rel
        if models_dir is None:
            models_dir = root / "models"
    models_dir = Path(models_dir)
    if not models_dir.is_dir():
        raise PerchError(f"models folder not found: {models_dir} (pass --models DIR)")
    info_file = models_dir / "models_info.json"
    models_info = load_models_info(info_file) if info_file.exists() else {}
    cam_file = root / "camera.json"
    camera_info = None
    if cam_file.exists():
        camera_info = read_json(cam_file, "camera.json")
        if not isinstance(camera_info, dict):
            raise PerchError(f"{cam_file} must hold a JSON object")
    ds = Dataset(root, split, models_dir, models_info, camera_info)
    if not ds.scene_ids():
        raise PerchError(f"no scene folders (000001, ...) in {split_dir}")
    return ds


def image_path(scene_dir: Path, im_id: int, kind: str = "rgb") -> Path | None:
    """`scene_dir/{kind}/{im_id:06d}.png|.jpg|...`, or None when absent."""
    for suffix in IMAGE_SUFFIXES:
        p = scene_dir / kind / f"{im_id:06d}{suffix}"
        if p.is_file():
            return p
    return None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the image header without decoding the pixels (size limits: `image.image_header_size`)."""
    return image_header_size(path)


def camera_for_image(ds: Dataset, entry: dict, rgb: Path, im_id: int, source: Path) -> Camera:
    """The image's `Camera`, refusing images whose size does not fit `cam_K` (or root camera.json);
    the principal-point rule is `camera_from_entry`'s, shared with the single-image command."""
    width, height = image_size(rgb)
    if ds.camera_info is not None:
        w0 = entry_size(ds.camera_info, "width", str(ds.root / "camera.json"))
        h0 = entry_size(ds.camera_info, "height", str(ds.root / "camera.json"))
        if w0 is not None and h0 is not None and (w0, h0) != (width, height):
            raise PerchError(f"image {rgb} is {width}x{height} but {ds.root / 'camera.json'} says {w0}x{h0}")
    return camera_from_entry(entry, width, height, source=f"{source} image {im_id}", image=str(rgb))


# ----------------------------------------------------------------------------- camera and depth files


def read_camera_json(path: str | Path, image_id: int | None = None) -> dict:
    """One camera entry from a BOP `scene_camera.json` (or a flat dict with `cam_K`).

    BOP files map image ids to entries; `image_id` picks one, and may be omitted when
    the file holds exactly one entry.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise PerchError(f"camera file not found: {path}") from None
    except (OSError, ValueError) as e:
        raise PerchError(f"cannot read camera file {path}: {e}") from None
    if not isinstance(data, dict):
        raise PerchError(f"camera file {path} must hold a JSON object")
    if "cam_K" in data:
        return data
    if image_id is not None:
        entry = data.get(str(image_id))
        if entry is None:
            raise PerchError(f"camera file {path} has no entry for image id {image_id} (has {sorted(data)[:10]})")
    elif len(data) == 1:
        entry = next(iter(data.values()))
    else:
        raise PerchError(f"camera file {path} has {len(data)} entries; say which with --image-id")
    if not isinstance(entry, dict) or "cam_K" not in entry:
        raise PerchError(f"camera entry in {path} has no 'cam_K'")
    return entry


def read_depth_mm(path: str | Path, depth_scale: float) -> np.ndarray:
    """A BOP depth PNG (uint16) as float32 millimetres (raw * depth_scale); 0 = no reading."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            raw = np.asarray(im)
    except FileNotFoundError:
        raise PerchError(f"depth image not found: {path}") from None
    except (UnidentifiedImageError, OSError) as e:
        raise PerchError(f"cannot read depth image {path}: {e}") from None
    if raw.ndim != 2:
        raise PerchError(f"depth image {path} must be single-channel (16-bit), got shape {raw.shape}")
    return raw.astype(np.float32) * np.float32(depth_scale)


# ----------------------------------------------------------------------------- results.csv


@dataclass(frozen=True)
class BopResult:
    """One row of a BOP results file. `t_mm` in millimetres (BOP), `time_s` seconds for the whole image."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t_mm: np.ndarray
    time_s: float = -1.0

    def line(self) -> str:
        # repr of a Python float round-trips exactly.
        R = " ".join(repr(float(v)) for v in np.asarray(self.R, dtype=np.float64).reshape(9))
        t = " ".join(repr(float(v)) for v in np.asarray(self.t_mm, dtype=np.float64).reshape(3))
        return f"{self.scene_id},{self.im_id},{self.obj_id},{float(self.score)!r},{R},{t},{float(self.time_s)!r}"


def write_json(path: str | Path, data) -> None:
    """A JSON file as the BOP tools write them (indent 1, final newline), atomically."""
    atomic_write_text(path, json.dumps(data, indent=1) + "\n")


def write_scene(
    scene_dir: str | Path,
    cameras: dict[int, dict],
    gts: dict[int, list[dict]],
    infos: dict[int, list[dict]] | None = None,
) -> None:
    """A scene's scene_camera.json, scene_gt.json [and scene_gt_info.json], keyed by image id (entries in BOP
    units, mm)."""
    scene_dir = Path(scene_dir)
    write_json(scene_dir / "scene_camera.json", {str(k): v for k, v in cameras.items()})
    write_json(scene_dir / "scene_gt.json", {str(k): v for k, v in gts.items()})
    if infos is not None:
        write_json(scene_dir / "scene_gt_info.json", {str(k): v for k, v in infos.items()})


def write_results(path: str | Path, results: list[BopResult]) -> None:
    """Write a whole results file atomically (unique temporary file, fsync, rename)."""
    atomic_write_text(path, "".join(line + "\n" for line in [RESULTS_HEADER, *(r.line() for r in results)]))


def read_results(path: str | Path) -> list[BopResult]:
    """Read a BOP results file; malformed lines raise PerchError naming file and line."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise PerchError(f"results file not found: {path}") from None
    except OSError as e:
        raise PerchError(f"cannot read results file {path}: {e}") from None
    if not lines or lines[0].strip() != RESULTS_HEADER:
        raise PerchError(f"{path}: first line must be the header {RESULTS_HEADER!r}")
    out = []
    for no, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        parts = line.split(",")
        try:
            if len(parts) != 7:
                raise ValueError(f"{len(parts)} comma-separated fields instead of 7")
            R = np.array([float(v) for v in parts[4].split()], dtype=np.float64)
            t = np.array([float(v) for v in parts[5].split()], dtype=np.float64)
            if R.size != 9 or t.size != 3:
                raise ValueError("R needs 9 values and t 3")
            ids = int(parts[0]), int(parts[1]), int(parts[2])
            out.append(BopResult(*ids, float(parts[3]), R.reshape(3, 3), t, float(parts[6])))
        except ValueError as e:
            raise PerchError(f"{path} line {no}: malformed result ({e})") from None
    return out
