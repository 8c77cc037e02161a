"""Camera models: projections against OpenCV, project/unproject round trips, valid ranges, YAML dictionaries."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from vo_core.errors import InputError
from vo_core.geometry.camera import (
    CameraModel,
    EquidistantCamera,
    FovCamera,
    PinholeCamera,
    RadTanCamera,
    camera_from_dict,
    camera_to_dict,
)
from vo_core.geometry.undistorter import Undistorter

# Published calibrations: EuRoC cam0 (sensor.yaml), TUM-VI-like fisheye lens on a narrower sensor, TUM monoVO
# sequence 01 (camera.txt, converted to absolute pixels), and a strong pincushion lens with all five terms.
EUROC = RadTanCamera(752, 480, 458.654, 457.296, 367.215, 248.375, -0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
PINCUSHION = RadTanCamera(640, 480, 500.0, 505.0, 318.0, 242.0, 0.3, 0.1, 0.001, -0.002, 0.05)
FISHEYE = EquidistantCamera(512, 512, 190.97, 190.98, 254.93, 256.89, 0.00348, 0.000715, -0.00205, 0.000203)
FISHEYE_NARROW = EquidistantCamera(640, 480, 300.0, 300.0, 320.0, 240.0, -0.01, 0.02, -0.005, 0.001)
FOV = FovCamera(640, 512, 0.535 * 640, 0.669 * 512, 0.493 * 640 - 0.5, 0.500 * 512 - 0.5, 0.897)
PINHOLE = PinholeCamera(640, 480, 520.0, 521.0, 319.5, 239.5)

ALL_CAMERAS = [EUROC, PINCUSHION, FISHEYE_NARROW, FOV, PINHOLE]
IDS = ["euroc", "pincushion", "fisheye", "fov", "pinhole"]


def pixel_grid(camera, step: float = 7.0) -> np.ndarray:
    u, v = np.meshgrid(np.arange(0.0, camera.width, step), np.arange(0.0, camera.height, step))
    return np.column_stack([u.ravel(), v.ravel()])


def points_in_view(camera, count: int = 500, seed: int = 3) -> np.ndarray:
    """Random 3D points at depths 0.5-20 m whose pixels cover the whole image."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0.0, 0.0], [camera.width - 1, camera.height - 1], size=(count, 2))
    depth = rng.uniform(0.5, 20.0, size=(count, 1))
    return camera.unproject(uv) * depth


def test_every_model_is_a_camera_model():
    for camera in ALL_CAMERAS:
        assert isinstance(camera, CameraModel)
        np.testing.assert_array_equal(camera.K, [[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])


@pytest.mark.parametrize("camera", [EUROC, PINCUSHION], ids=["euroc", "pincushion"])
def test_radtan_projection_matches_opencv(camera):
    points = points_in_view(camera)
    ours = camera.project(points)
    theirs, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, np.array(camera.distortion))
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("camera", [FISHEYE, FISHEYE_NARROW], ids=["wide", "narrow"])
def test_equidistant_projection_matches_opencv_fisheye(camera):
    uv = pixel_grid(camera, 13.0)
    points = camera.unproject(uv)
    points = points[np.isfinite(points[:, 0])] * 2.0
    ours = camera.project(points)
    theirs, _ = cv2.fisheye.projectPoints(
        points.reshape(1, -1, 3), np.zeros(3), np.zeros(3), camera.K, np.array(camera.distortion)
    )
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-9)


def test_radtan_unprojection_matches_opencv_iterative_undistortion():
    uv = pixel_grid(EUROC, 31.0)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
    theirs = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), EUROC.K, np.array(EUROC.distortion), None, None, criteria)
    np.testing.assert_allclose(EUROC.unproject(uv)[:, :2], theirs.reshape(-1, 2), atol=1e-8)


def test_fov_matches_dso_formula():
    """DSO's UndistortFOV::distortCoordinates: r_d = atan(2 r tan(omega / 2)) / omega, u = fx r_d / r x + cx."""
    x, y = 0.4, -0.3
    r = np.hypot(x, y)
    factor = np.arctan(r * 2.0 * np.tan(FOV.omega / 2.0)) / (FOV.omega * r)
    expected = [FOV.fx * factor * x + FOV.cx, FOV.fy * factor * y + FOV.cy]
    np.testing.assert_allclose(FOV.project(np.array([[x, y, 1.0]])), [expected], atol=1e-12)
    # On the optical axis the distortion vanishes.
    np.testing.assert_allclose(FOV.project(np.array([[0.0, 0.0, 2.0]])), [[FOV.cx, FOV.cy]], atol=1e-12)


@pytest.mark.parametrize("camera", ALL_CAMERAS, ids=IDS)
def test_project_of_unproject_is_identity_over_the_image(camera):
    uv = pixel_grid(camera)
    rays = camera.unproject(uv)
    assert np.all(np.isfinite(rays))
    np.testing.assert_array_equal(rays[:, 2], 1.0)
    np.testing.assert_allclose(camera.project(rays), uv, atol=1e-9)


@pytest.mark.parametrize("camera", ALL_CAMERAS, ids=IDS)
def test_unproject_of_project_recovers_the_ray(camera):
    points = points_in_view(camera)
    np.testing.assert_allclose(camera.unproject(camera.project(points)), points / points[:, 2:3], atol=1e-9)


def test_radtan_and_fov_without_distortion_equal_the_pinhole():
    params = (PINHOLE.width, PINHOLE.height, PINHOLE.fx, PINHOLE.fy, PINHOLE.cx, PINHOLE.cy)
    points, uv = points_in_view(PINHOLE), pixel_grid(PINHOLE)
    for camera in (RadTanCamera(*params, 0, 0, 0, 0), FovCamera(*params, 0.0)):
        assert camera.pinhole == PINHOLE
        np.testing.assert_allclose(camera.project(points), PINHOLE.project(points), atol=1e-9)
        np.testing.assert_allclose(camera.unproject(uv), PINHOLE.unproject(uv), atol=1e-12)


def test_ideal_fisheye_maps_angle_linearly():
    """With no coefficients the equidistant model is r_d = theta: a ray at 90 deg lands fx * pi / 2 from the centre."""
    camera = EquidistantCamera(640, 480, 100.0, 100.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0)
    uv = camera.project(np.array([[1.0, 0.0, 0.0], [0.0, -1.0, -1.0]]))
    np.testing.assert_allclose(uv, [[320.0 + 100.0 * np.pi / 2, 240.0], [320.0, 240.0 - 100.0 * 3 * np.pi / 4]])


def test_rays_outside_the_valid_range_project_to_nan():
    behind = np.array([[0.1, 0.2, -1.0]])
    assert np.all(np.isnan(EUROC.project(behind)))
    assert np.all(np.isnan(FOV.project(behind)))
    # Strong barrel distortion folds back at r^2 = 1 / (3 * 0.5): a ray beyond would land inside the image.
    folding = RadTanCamera(640, 480, 300.0, 300.0, 320.0, 240.0, -0.5, 0.0, 0.0, 0.0)
    assert folding.max_radius_squared == pytest.approx(1.0 / 1.5)
    beyond = np.array([[1.2, 0.0, 1.0]])
    naive_u = 300.0 * 1.2 * (1.0 - 0.5 * 1.44) + 320.0
    assert 0.0 <= naive_u < 640.0
    assert np.all(np.isnan(folding.project(beyond)))
    # A pixel beyond the fold's image (r_d > r_max (1 - 0.5 r_max^2)) is reached by no ray.
    assert np.all(np.isnan(folding.unproject(np.array([[320.0 + 300.0 * 0.6, 240.0]]))))
    assert np.all(np.isfinite(folding.unproject(np.array([[320.0 + 300.0 * 0.5, 240.0]]))))


def test_wide_fisheye_pixels_beyond_ninety_degrees_do_not_unproject_to_the_plane():
    uv = pixel_grid(FISHEYE)
    rays = FISHEYE.unproject(uv)
    beyond = np.isnan(rays[:, 0])
    assert beyond.any() and not beyond.all()
    theta_d = np.hypot((uv[:, 0] - FISHEYE.cx) / FISHEYE.fx, (uv[:, 1] - FISHEYE.cy) / FISHEYE.fy)
    # Only pixels far from the centre (theta_d ~ pi / 2 or more) are lost.
    assert theta_d[beyond].min() > 1.5


# ----------------------------------------------------------------------------------------------- dictionaries


@pytest.mark.parametrize("camera", ALL_CAMERAS + [FISHEYE], ids=IDS + ["wide"])
def test_dictionary_round_trip_through_yaml(camera):
    text = yaml.safe_dump(camera_to_dict(camera))
    assert camera_from_dict(yaml.safe_load(text), "cam.yaml") == camera


def test_radtan_accepts_four_coefficients():
    d = {"model": "radtan", "intrinsics": [458.654, 457.296, 367.215, 248.375], "resolution": [752, 480]}
    d["distortion"] = [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
    assert camera_from_dict(d) == EUROC


def test_pinhole_needs_no_distortion_key():
    d = {"model": "pinhole", "intrinsics": [520.0, 521.0, 319.5, 239.5], "resolution": [640, 480]}
    assert camera_from_dict(d) == PINHOLE


GOOD = {"model": "fov", "intrinsics": [500.0, 500.0, 320.0, 240.0], "distortion": [0.9], "resolution": [640, 480]}


@pytest.mark.parametrize(
    "change,message",
    [
        ({"model": None}, "missing model"),
        ({"intrinsics": None, "resolution": None}, "missing intrinsics, resolution"),
        ({"model": "kb8"}, "unknown camera model 'kb8'"),
        ({"intrinsics": [500.0, 500.0, 320.0]}, "'intrinsics' must be 4 numbers"),
        ({"intrinsics": [500.0, "a", 320.0, 240.0]}, "'intrinsics' must be 4 numbers"),
        ({"intrinsics": 500.0}, "'intrinsics' must be 4 numbers"),
        ({"distortion": [0.9, 0.1]}, "'distortion' must be 1 numbers for model fov"),
        ({"model": "radtan"}, "'distortion' must be 4 or 5 numbers for model radtan"),
        ({"model": "equidistant", "distortion": None}, "'distortion' must be 4 numbers"),
        ({"model": "pinhole"}, "'distortion' must be 0 numbers"),
        ({"intrinsics": [0.0, 500.0, 320.0, 240.0]}, "focal lengths must be positive"),
        ({"intrinsics": [500.0, -1.0, 320.0, 240.0]}, "focal lengths must be positive"),
        ({"intrinsics": [500.0, 500.0, float("nan"), 240.0]}, "'intrinsics' must be 4 numbers"),
        ({"resolution": [640, 0]}, "resolution must be two positive integers"),
        ({"resolution": [640.5, 480]}, "resolution must be two positive integers"),
        ({"resolution": [640]}, "'resolution' must be 2 numbers"),
    ],
)
def test_malformed_dictionaries_name_the_source(change, message):
    d = {**GOOD, **change}
    d = {key: value for key, value in d.items() if value is not None}
    with pytest.raises(InputError, match=f"^calib/cam.yaml: .*{message}"):
        camera_from_dict(d, "calib/cam.yaml")


def test_non_mapping_is_refused():
    with pytest.raises(InputError, match="^cam.yaml: a camera must be a mapping"):
        camera_from_dict([1, 2, 3], "cam.yaml")


# ----------------------------------------------------------------------------------------------- undistorter

DISTORTED = [EUROC, PINCUSHION, FISHEYE_NARROW, FOV]
DISTORTED_IDS = ["euroc", "pincushion", "fisheye", "fov"]
BLOB_DIRECTIONS = np.array([[0.0, 0.0], [0.25, -0.2], [-0.3, 0.15], [0.2, 0.25], [-0.2, -0.25]])


def image_border(camera) -> np.ndarray:
    """The centres of all pixels on the image border."""
    u, v = np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float)
    right, bottom = np.full_like(v, camera.width - 1), np.full_like(u, camera.height - 1)
    return np.concatenate([np.column_stack([u, 0 * u]), np.column_stack([u, bottom]),
                           np.column_stack([0 * v, v]), np.column_stack([right, v])])


def render(camera, scene) -> np.ndarray:
    """Sample a scene defined on the normalized plane z = 1 at every pixel centre of ``camera``."""
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    rays = camera.unproject(np.column_stack([u.ravel(), v.ravel()]))
    return scene(rays[:, 0], rays[:, 1]).reshape(camera.height, camera.width).astype(np.float32)


def waves(x, y):
    """Smooth texture, periodic in the ray's angles (wavelength 0.15 rad): tens of pixels in every camera here,
    fisheye periphery included."""
    return 128.0 + 60.0 * np.sin(2 * np.pi * np.arctan(x) / 0.15) * np.cos(2 * np.pi * np.arctan(y) / 0.15)


def blobs(x, y):
    """Round blobs on the normalized plane around BLOB_DIRECTIONS: their centroids are known in any pinhole."""
    image = np.zeros_like(x)
    for bx, by in BLOB_DIRECTIONS:
        image += 255.0 * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * 0.006**2))
    return image


@pytest.mark.parametrize("camera", DISTORTED, ids=DISTORTED_IDS)
@pytest.mark.parametrize("output", ["crop", "full", "none", (400, 300)])
def test_rectified_image_is_the_pinhole_rendering(camera, output):
    undistorter = Undistorter(camera, output)
    rectified = undistorter.rectify(render(camera, waves))
    expected = render(undistorter.camera, waves)
    valid = undistorter.valid_mask
    assert rectified.dtype == np.float32 and rectified.shape == expected.shape
    # Bilinear sampling of a 60-level wave at 1/32 px: well under a grey level of error.
    assert np.abs(rectified - expected)[valid].max() < 1.0
    np.testing.assert_array_equal(rectified[~valid], 0.0)


@pytest.mark.parametrize("camera", DISTORTED, ids=DISTORTED_IDS)
def test_points_land_where_the_target_camera_projects_them(camera):
    undistorter = Undistorter(camera, "crop")
    rectified = undistorter.rectify(render(camera, blobs))
    target = undistorter.camera
    expected = target.project(np.column_stack([BLOB_DIRECTIONS, np.ones(len(BLOB_DIRECTIONS))]))
    u, v = np.meshgrid(np.arange(target.width), np.arange(target.height))
    for eu, ev in expected:
        window = (np.abs(u - eu) < 25) & (np.abs(v - ev) < 25)
        weights = rectified * window
        centroid = [np.sum(weights * u) / weights.sum(), np.sum(weights * v) / weights.sum()]
        np.testing.assert_allclose(centroid, [eu, ev], atol=0.05)


@pytest.mark.parametrize("camera", DISTORTED, ids=DISTORTED_IDS)
def test_crop_has_no_invalid_border(camera):
    undistorter = Undistorter(camera, "crop")
    assert undistorter.valid_mask.all()
    white = np.full((camera.height, camera.width), 255, np.uint8)
    rectified = undistorter.rectify(white)
    assert rectified.dtype == np.uint8 and rectified.min() == 255
    # Crop is tight: 2% more field of view on every side would see outside the raw image.
    crop = undistorter.camera
    wider = PinholeCamera(crop.width, crop.height, crop.fx / 1.04, crop.fy / 1.04, crop.cx, crop.cy)
    raw_uv = camera.project(wider.unproject(image_border(wider)))
    assert np.any((raw_uv < 0) | (raw_uv > [camera.width - 1, camera.height - 1]))


@pytest.mark.parametrize("camera", DISTORTED, ids=DISTORTED_IDS)
def test_full_shows_the_whole_raw_image(camera):
    target = Undistorter(camera, "full").camera
    seen = target.project(camera.unproject(image_border(camera)))
    assert np.all(seen >= -1e-6) and np.all(seen <= [target.width - 1 + 1e-6, target.height - 1 + 1e-6])


def test_given_size_keeps_the_crop_field_of_view():
    crop = Undistorter(EUROC, "crop").camera
    for output in ((376, 240), "376x240", [1000, 700]):
        sized = Undistorter(EUROC, output).camera
        corners = np.array([[0.0, 0.0], [sized.width - 1, sized.height - 1]])
        crop_corners = np.array([[0.0, 0.0], [crop.width - 1, crop.height - 1]])
        np.testing.assert_allclose(sized.unproject(corners), crop.unproject(crop_corners), atol=1e-12)


def test_explicit_target_camera_is_used_as_given():
    """TUM monoVO's camera.txt names the output pinhole (DSO's line 3 "fx fy cx cy 0")."""
    target = PinholeCamera(376, 240, 200.0, 240.0, 187.5, 119.5)
    undistorter = Undistorter(EUROC, target)
    assert undistorter.camera == target and undistorter.valid_mask.all()
    np.testing.assert_array_less(np.abs(undistorter.rectify(render(EUROC, waves)) - render(target, waves)), 1.0)
    assert Undistorter(PINHOLE, PinholeCamera(*vars(PINHOLE).values())).is_identity


def test_none_keeps_the_raw_pinhole_part():
    assert Undistorter(EUROC, "none").camera == EUROC.pinhole


@pytest.mark.parametrize("output", ["crop", "none", "full"])
def test_pinhole_input_is_passed_through(output):
    undistorter = Undistorter(PINHOLE, output)
    assert undistorter.is_identity and undistorter.camera == PINHOLE and undistorter.valid_mask.all()
    image = np.zeros((PINHOLE.height, PINHOLE.width), np.uint8)
    assert undistorter.rectify(image) is image


def test_pinhole_to_a_given_size_resamples():
    undistorter = Undistorter(PINHOLE, (320, 240))
    assert not undistorter.is_identity
    rectified = undistorter.rectify(render(PINHOLE, waves))
    assert np.abs(rectified - render(undistorter.camera, waves)).max() < 1.0


@pytest.mark.parametrize("output", ["wide", "640x", (640,), (0, 480), "10x1", (640.5, 480)])
def test_bad_output_is_refused(output):
    with pytest.raises(InputError, match="undistort output"):
        Undistorter(EUROC, output)


def test_image_of_the_wrong_size_is_refused():
    with pytest.raises(ValueError, match="image of 640x480 pixels given to an undistorter for 752x480"):
        Undistorter(EUROC).rectify(np.zeros((480, 640), np.uint8))
