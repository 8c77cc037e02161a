"""Synthetic sequences: determinism, exact depth and poses, photometric consistency between views, texture that
both halves of the odometry can use, and the motion each trajectory preset promises."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from vo_core.datasets import Frame
from vo_core.errors import InputError
from vo_core.geometry.lie import se3, se3_inverse, so3_exp, so3_log, transform_points
from vo_core.synthetic import (
    PRESETS,
    Renderer,
    default_camera,
    make_sequence,
    make_trajectory,
    plane_scene,
    room_scene,
)

SMALL = {"width": 320, "height": 240}


@pytest.fixture(scope="module")
def smooth():
    return make_sequence("smooth", 8, seed=0, **SMALL)


@pytest.fixture(scope="module")
def room_renderer():
    return Renderer(room_scene(0), default_camera(**SMALL))


# ------------------------------------------------------------------------------------------ determinism


def test_same_seed_renders_the_same_frames_and_another_seed_other_ones():
    first, again, other = (make_sequence("smooth", 3, seed=seed, width=160, height=120) for seed in (5, 5, 6))
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.T_world_cam, b.T_world_cam)
    assert np.abs(first[2].image.astype(float) - other[2].image).mean() > 10.0
    assert not np.allclose(first.ground_truth.poses, other.ground_truth.poses)
    # Scenes are cached per seed: textures drawn afresh must be the cached ones.
    for fresh, cached in zip(room_scene.__wrapped__(5).planes, room_scene(5).planes):
        np.testing.assert_array_equal(fresh.texture, cached.texture)


# ------------------------------------------------------------------------------------------ exact geometry


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``image`` interpolated at the (N, 2) pixel positions ``uv``, in float64 (cv2.remap rounds positions to
    1/32 pixel, too coarse for exact comparisons)."""
    corner = np.floor(uv).astype(int)
    fx, fy = (uv - corner).T
    x, y = corner.T
    image = image.astype(float)
    top = (1 - fx) * image[y, x] + fx * image[y, x + 1]
    bottom = (1 - fx) * image[y + 1, x] + fx * image[y + 1, x + 1]
    return (1 - fy) * top + fy * bottom


def _world_points_of_pixels(depth: np.ndarray, T_world_cam: np.ndarray, camera) -> np.ndarray:
    """(H, W, 3) world points of the pixel centres at their depths."""
    rows, columns = np.mgrid[0 : camera.height, 0 : camera.width]
    uv = np.column_stack([columns.ravel(), rows.ravel()]).astype(float)
    points_cam = camera.unproject(uv) * depth.reshape(-1, 1)
    return transform_points(T_world_cam, points_cam).reshape(camera.height, camera.width, 3)


def _ray_cast(scene, camera, T_world_cam) -> np.ndarray:
    """Depth by brute force in float64: every pixel's ray against every rectangle, the nearest hit kept."""
    rows, columns = np.mgrid[0 : camera.height, 0 : camera.width]
    rays = camera.unproject(np.column_stack([columns.ravel(), rows.ravel()]).astype(float)) @ T_world_cam[:3, :3].T
    centre = T_world_cam[:3, 3]
    depth = np.full(len(rays), np.inf)
    for plane in scene.planes:
        with np.errstate(divide="ignore", invalid="ignore"):
            z = ((plane.origin - centre) @ plane.normal) / (rays @ plane.normal)  # rays have camera z = 1
        relative = centre + z[:, None] * rays - plane.origin
        a, b = relative @ plane.axis_u, relative @ plane.axis_v
        hit = (z > 0) & (a >= 0) & (a <= plane.width_m) & (b >= 0) & (b <= plane.height_m)
        depth = np.where(hit & (z < depth), z, depth)
    return depth.reshape(camera.height, camera.width)


POSES = [np.eye(4), se3(so3_exp(np.array([0.05, -0.2, 0.03])), np.array([0.3, -0.1, 0.2]))]


@pytest.mark.parametrize("pose", POSES)
def test_depth_is_that_of_the_nearest_surface_on_each_pixel_ray(pose):
    scene, camera = room_scene(0), default_camera(160, 120)
    depth = Renderer(scene, camera).render(pose).depth
    reference = _ray_cast(scene, camera, pose)
    assert np.isfinite(reference).all()  # the closed room fills the view
    exact = np.abs(depth - reference) <= 1e-5 * reference  # float32 inverse depth
    assert exact.mean() > 0.999  # all but pixel centres within round-off of a silhouette


@pytest.mark.parametrize("pose", POSES)
def test_surface_points_project_where_the_depth_map_has_their_depth(room_renderer, pose):
    """A point of a plane, projected with the true pose, falls among pixels whose depths interpolate to its z
    (inverse depth is affine on a plane, so its bilinear interpolation is exact) wherever the plane is visible."""
    camera, rng = room_renderer.camera, np.random.default_rng(0)
    depth = room_renderer.render(pose).depth
    on_plane_pixels = _world_points_of_pixels(depth, pose, camera)
    T_cam_world = se3_inverse(pose)
    visible_count = 0
    for plane in room_renderer.scene.planes:
        a = rng.uniform(0, plane.width_m, 300)
        b = rng.uniform(0, plane.height_m, 300)
        points_cam = transform_points(T_cam_world, plane.origin + a[:, None] * plane.axis_u + b[:, None] * plane.axis_v)
        uv = camera.project(points_cam[points_cam[:, 2] > 0.1])
        z = points_cam[points_cam[:, 2] > 0.1, 2][camera.in_image(uv, border=1.0)]
        uv = uv[camera.in_image(uv, border=1.0)]
        # Visible: the four pixels around the projection see this plane.
        x, y = np.floor(uv).astype(int).T
        neighbours = [on_plane_pixels[y + dy, x + dx] for dy in (0, 1) for dx in (0, 1)]
        visible = np.max([np.abs((p - plane.origin) @ plane.normal) for p in neighbours], axis=0) < 1e-5
        interpolated = _bilinear(1.0 / depth, uv[visible])
        np.testing.assert_allclose(interpolated, 1.0 / z[visible], rtol=1e-5)
        visible_count += visible.sum()
    assert visible_count > 1000


def test_corresponding_pixels_of_two_views_have_the_same_intensity(smooth):
    """The photometric consistency that direct tracking relies on: warping with true depth and poses."""
    a, b, camera = smooth[0], smooth[3], smooth.camera
    rows, columns = np.mgrid[4 : camera.height - 4 : 2, 4 : camera.width - 4 : 2]
    rows, columns = rows.ravel(), columns.ravel()
    points_a = camera.unproject(np.column_stack([columns, rows]).astype(float)) * a.depth[rows, columns, None]
    points_b = transform_points(se3_inverse(b.T_world_cam) @ a.T_world_cam, points_a)
    uv_b = camera.project(points_b)
    inside = camera.in_image(uv_b, border=2.0)
    uv_b, z_b = uv_b[inside], points_b[inside, 2]
    # Visible in b (not occluded there) and away from depth discontinuities, where the blur mixes surfaces.
    nearest = np.rint(uv_b).astype(int)
    depth_b = b.depth[nearest[:, 1], nearest[:, 0]]
    unoccluded = np.abs(depth_b - z_b) < 0.01 * z_b
    depth_range = cv2.dilate(b.depth, np.ones((5, 5))) - cv2.erode(b.depth, np.ones((5, 5)))
    smooth_depth = depth_range[nearest[:, 1], nearest[:, 0]] < 0.05 * depth_b
    keep = unoccluded & smooth_depth
    warped = _bilinear(b.image, uv_b[keep])
    difference = np.abs(warped - a.image[rows[inside][keep], columns[inside][keep]])
    assert keep.sum() > 0.8 * len(rows)
    assert np.median(difference) < 1.0 and np.percentile(difference, 90) < 3.0  # gray levels


def test_brightness_change_is_the_affine_map_the_frame_reports():
    plain = make_sequence("static", 12, seed=1, width=160, height=120)
    changed = make_sequence("static", 12, seed=1, width=160, height=120, brightness_change=True)
    gains = [changed[i].gain for i in range(0, 12, 4)]
    assert np.ptp(gains) > 0.01 and all(0.8 < gain < 1.2 for gain in gains)
    frame, reference = changed[11], plain[11].image.astype(float)
    expected = np.clip(frame.gain * reference + frame.offset, 0, 255)
    # Each image is rounded to integers: the reference's rounding is scaled by the gain, then the frame's added.
    assert np.abs(frame.image - expected).max() <= 0.5 * (1.0 + frame.gain) + 1e-6


def test_pixels_that_see_nothing_have_infinite_depth():
    camera = default_camera(64, 48)
    looking_away = se3(so3_exp(np.array([0.0, np.pi, 0.0])), np.zeros(3))
    rendering = Renderer(plane_scene(0), camera).render(looking_away)
    assert np.isinf(rendering.depth).all() and not rendering.image.any()


# ------------------------------------------------------------------------------------ texture for both halves


@pytest.mark.parametrize("preset", ["smooth", "planar"])
def test_full_size_frames_have_gradients_everywhere_and_corners_all_over(preset):
    image = make_sequence(preset, 1, seed=2)[0].image
    gray = image.astype(np.float32)
    gradient = np.hypot(*np.gradient(gray))  # central differences, gray levels per pixel
    blocks = gradient[: 480 // 32 * 32, : 640 // 32 * 32].reshape(15, 32, 20, 32).transpose(0, 2, 1, 3)
    block_medians = np.median(blocks.reshape(15, 20, -1), axis=2)
    assert np.mean(block_medians > 2.0) > 0.9  # DSO selects points in 32x32 blocks by their median gradient
    keypoints = cv2.ORB_create(nfeatures=2000).detect(image, None)
    cells = {(int(k.pt[0] // 160), int(k.pt[1] // 120)) for k in keypoints}
    assert len(keypoints) >= 300 and len(cells) == 16  # every cell of a 4x4 grid


# ------------------------------------------------------------------------------------------------- presets


def _steps(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation angle (rad) between consecutive poses."""
    relative = [se3_inverse(a) @ b for a, b in zip(poses[:-1], poses[1:])]
    return (np.array([np.linalg.norm(T[:3, 3]) for T in relative]),
            np.array([np.linalg.norm(so3_log(T[:3, :3])) for T in relative]))


@pytest.mark.parametrize("preset", PRESETS)
def test_each_preset_gives_the_frames_asked_for_in_time_order(preset):
    trajectory = make_trajectory(preset, 40, seed=3)
    assert len(trajectory.timestamps) == len(trajectory.poses) == len(trajectory.frame_numbers) == 40
    assert np.all(np.diff(trajectory.timestamps) > 0)
    rotations = trajectory.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.tile(np.eye(3), (40, 1, 1)), atol=1e-12)


def test_smooth_motion_moves_like_a_hand_held_camera():
    translation, rotation = _steps(make_trajectory("smooth", 90, seed=4).poses)
    assert 0.005 < np.median(translation) < 0.05  # metres a frame at 30 Hz
    assert np.radians(0.1) < np.median(rotation) < np.radians(3.0)
    assert translation.max() < 3 * np.median(translation)  # smooth: no jumps


def test_rotation_keeps_the_camera_centre_fixed():
    poses = make_trajectory("rotation", 60, seed=5).poses
    np.testing.assert_allclose(poses[:, :3, 3], 0.0, atol=1e-12)
    _, rotation = _steps(poses)
    assert np.degrees(rotation.sum()) > 10.0


def test_forward_moves_along_the_optical_axis():
    poses = make_trajectory("forward", 30, seed=6).poses
    for a, b in zip(poses[:-1], poses[1:]):
        step = se3_inverse(a) @ b  # the motion in the first camera's frame
        np.testing.assert_allclose(step[:3, :3], np.eye(3), atol=1e-12)
        assert step[2, 3] > 0.01 and np.linalg.norm(step[:2, 3]) < 1e-12


def test_static_never_moves():
    poses = make_trajectory("static", 10, seed=7).poses
    assert np.all(poses == poses[0])


def test_jump_leaves_out_a_block_of_frames_for_a_large_baseline():
    trajectory = make_trajectory("jump", 40, seed=8)
    translation, rotation = _steps(trajectory.poses)
    gap = int(np.argmax(np.diff(trajectory.frame_numbers)))
    assert np.diff(trajectory.frame_numbers)[gap] == len(trajectory.dropped) + 1 > 5
    interval = trajectory.timestamps[gap + 1] - trajectory.timestamps[gap]
    assert interval == pytest.approx((len(trajectory.dropped) + 1) / 30)
    others = np.delete(translation, gap)
    assert translation[gap] > 5 * np.median(others) and rotation[gap] > 3 * np.median(np.delete(rotation, gap))


def test_loop_ends_where_it_starts():
    poses = make_trajectory("loop", 90, seed=9).poses
    translation, rotation = _steps(poses)
    # From the last frame back to the first is one more ordinary step: played twice, the loop moves on smoothly.
    closing_translation, closing_rotation = _steps(np.stack([poses[-1], poses[0]]))
    assert closing_translation[0] < 2 * np.median(translation) and closing_rotation[0] < 2 * np.median(rotation)
    assert np.ptp(poses[:, :3, 3], axis=0).max() > 0.5  # a loop through the room, not a wobble in place
    assert translation.max() < 3 * np.median(translation)


@pytest.mark.parametrize("preset", ["smooth", "forward", "rotation", "planar", "jump", "loop"])
def test_the_scene_fills_every_view_of_the_preset(preset):
    sequence = make_sequence(preset, 45, seed=0, width=64, height=48)
    assert all(np.isfinite(frame.depth).all() for frame in sequence)


def test_planar_preset_sees_a_single_plane():
    sequence = make_sequence("planar", 2, seed=0, width=64, height=48)
    assert len(sequence.renderer.scene.planes) == 1
    plane = sequence.renderer.scene.planes[0]
    frame = sequence[1]
    points = _world_points_of_pixels(frame.depth, frame.T_world_cam, sequence.camera)
    np.testing.assert_allclose((points - plane.origin) @ plane.normal, 0.0, atol=1e-5)


# ------------------------------------------------------------------------------------- dataset behaviour


def test_sequence_behaves_like_a_dataset_sequence(smooth):
    assert smooth.layout == "synthetic" and len(smooth) == 8 and smooth.camera.fx == pytest.approx(250.0)
    frames = list(smooth)
    assert all(isinstance(frame, Frame) for frame in frames)
    assert [frame.index for frame in frames] == list(range(8))
    np.testing.assert_allclose([frame.timestamp for frame in frames], smooth.timestamps)
    np.testing.assert_array_equal(smooth.ground_truth.poses[3], frames[3].T_world_cam)
    assert frames[3].image.dtype == np.uint8 and frames[3].irradiance.dtype == np.float32
    assert frames[3].depth.dtype == np.float32 and frames[3].image.shape == frames[3].depth.shape == (240, 320)
    np.testing.assert_array_equal(smooth[-1].image, frames[-1].image)
    view = smooth.cut(2, 6, 2)
    assert list(view.indices) == [2, 4] and view[1].index == 4 and len(view.ground_truth) == 2
    assert [frame.index for frame in smooth.cut(0, 3).reversed()] == [2, 1, 0]
    description = json.loads(json.dumps(smooth.describe()))
    assert description["frames"] == 8 and description["resolution"] == [320, 240]


def test_jump_frames_keep_their_frame_numbers():
    sequence = make_sequence("jump", 6, seed=0, width=32, height=24)
    dropped = list(sequence.trajectory.dropped)
    assert [frame.index for frame in sequence] == [0, 1, 2] + [3 + len(dropped) + i for i in range(3)]
    assert sequence.describe()["dropped_frames"] == dropped


def test_unknown_preset_and_empty_sequences_are_refused_with_a_clear_message():
    with pytest.raises(InputError, match="unknown synthetic preset 'spiral'.*smooth"):
        make_sequence("spiral")
    with pytest.raises(InputError, match="at least one frame"):
        make_trajectory("smooth", 0)
    with pytest.raises(InputError, match="leaves none"):
        make_sequence("static", 3, width=32, height=24).cut(5, 9)
