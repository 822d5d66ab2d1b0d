import json

import numpy as np
import pytest

from perch_warp.bop import read_camera_json
from perch_warp.camera import Camera, camera_from_entry
from perch_warp.errors import PerchError

K = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]


def test_reads_bop_scene_camera(tmp_path):
    p = tmp_path / "scene_camera.json"
    p.write_text(json.dumps({"3": {"cam_K": K}, "4": {"cam_K": K}}))
    entry = read_camera_json(p, 4)
    cam = camera_from_entry(entry, 640, 480)
    assert cam.fx == 500 and cam.cy == 240
    with pytest.raises(PerchError, match="--image-id"):
        read_camera_json(p)
    with pytest.raises(PerchError, match="no entry for image id 5"):
        read_camera_json(p, 5)


def test_projection_matches_pinhole_formula():
    cam = Camera(np.array(K).reshape(3, 3), 640, 480)
    assert np.allclose(cam.project(np.array([0.1, -0.2, 2.0])), [320 + 25, 240 - 50])


@pytest.mark.parametrize(
    "k, match",
    [
        ([float("nan")] + K[1:], "finite"),
        ([0.0] + K[1:], "focal"),
        (K[:2] + [900.0] + K[3:], "outside"),
    ],
)
def test_bad_intrinsics_are_refused(k, match):
    with pytest.raises(PerchError, match=match):
        camera_from_entry({"cam_K": k}, 640, 480)


def test_size_in_file_must_match_image():
    with pytest.raises(PerchError, match="width"):
        camera_from_entry({"cam_K": K, "width": 800}, 640, 480)


def test_scaled_camera_keeps_pixel_centres_consistent():
    cam = Camera(np.array(K).reshape(3, 3), 640, 480)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    X = np.array([0.05, -0.03, 0.7])
    # A full-size pixel centre u maps to (u + 0.5) / 2 - 0.5 at half size (area resampling).
    assert np.allclose(half.project(X), (cam.project(X) + 0.5) * 0.5 - 0.5)
