"""Dataset loaders on tiny folders generated here: layouts detected, calibrations, timestamps, ground truth, and
every kind of bad input giving a one-line InputError (or a skipped frame) that names the file."""

from __future__ import annotations

import gc
import json
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from vo_core.datasets import DEFAULT_SEQUENCE, LAYOUTS, open_sequence
from vo_core.datasets.tum_rgbd import FREIBURG_CAMERAS
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera, RadTanCamera

FR3 = FREIBURG_CAMERAS[3]


def write_images(paths: list[Path], width: int, height: int, seed: int = 0) -> list[np.ndarray]:
    """Smooth random gray images (small PNGs), each different, written to ``paths``."""
    rng = np.random.default_rng(seed)
    images = []
    for path in paths:
        coarse = rng.integers(0, 256, size=(max(2, height // 8), max(2, width // 8)), dtype=np.uint8)
        image = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_LINEAR)
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), image)
        images.append(image)
    return images


def tum_quaternion_line(t: float, position, quaternion_xyzw) -> str:
    return " ".join(f"{v:.6f}" for v in (t, *position, *quaternion_xyzw))


def make_tum_rgbd(root: Path, count: int = 4, bag: str = "rgbd_dataset_freiburg3_teddy", gt_times=None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    times = 100.0 + np.arange(count) / 30.0
    names = [f"rgb/{t:.6f}.png" for t in times]
    write_images([root / n for n in names], 640, 480)
    header = f"# color images\n# file: '{bag}.bag'\n# timestamp filename\n"
    (root / "rgb.txt").write_text(header + "".join(f"{t:.6f} {n}\n" for t, n in zip(times, names)))
    gt_times = np.arange(99.9, 100.3, 0.01) if gt_times is None else gt_times
    lines = [tum_quaternion_line(t, (t - 100.0, 0.0, 1.0), (0, 0, 0, 1)) for t in gt_times]
    (root / "groundtruth.txt").write_text("# ground truth trajectory\n" + "\n".join(lines) + "\n")
    return root


# ------------------------------------------------------------------------------------------------ TUM RGB-D


def test_tum_rgbd_reads_frames_camera_and_ground_truth(tmp_path):
    sequence = open_sequence(make_tum_rgbd(tmp_path / "seq"))
    assert sequence.layout == "tum_rgbd" and len(sequence) == 4
    assert sequence.camera == FR3 and sequence.raw_camera == FR3
    np.testing.assert_allclose(sequence.timestamps, 100.0 + np.arange(4) / 30.0)
    frame = sequence[1]
    assert frame.index == 1 and frame.image.dtype == np.uint8 and frame.image.shape == (480, 640)
    assert frame.irradiance.dtype == np.float32 and np.array_equal(frame.irradiance, frame.image)
    assert frame.error is None and frame.path.endswith(f"{100 + 1 / 30:.6f}.png")
    assert len(sequence.ground_truth) == 40
    np.testing.assert_allclose(sequence.ground_truth.poses[10][:3, 3], [0.0, 0.0, 1.0], atol=1e-9)


def test_tum_rgbd_camera_from_folder_name_and_override_file(tmp_path):
    root = make_tum_rgbd(tmp_path / "rgbd_dataset_freiburg1_desk", bag="something_else")
    assert open_sequence(root).raw_camera == FREIBURG_CAMERAS[1]
    assert isinstance(FREIBURG_CAMERAS[1], RadTanCamera)
    (root / "camera.yaml").write_text("model: pinhole\nintrinsics: [500, 501, 320, 240]\nresolution: [640, 480]\n")
    assert open_sequence(root).camera == PinholeCamera(640, 480, 500, 501, 320, 240)


def test_tum_rgbd_unknown_camera_is_refused(tmp_path):
    root = make_tum_rgbd(tmp_path / "my_recording", bag="my_recording")
    with pytest.raises(InputError, match=r"rgb\.txt: cannot tell which TUM camera"):
        open_sequence(root)


def test_ground_truth_that_does_not_overlap_the_images_is_refused(tmp_path):
    root = make_tum_rgbd(tmp_path / "seq", gt_times=np.arange(200.0, 201.0, 0.01))
    with pytest.raises(InputError, match=r"groundtruth\.txt: .*does not overlap the images"):
        open_sequence(root)


@pytest.mark.parametrize("swap, word", [((1, 2), "out of order"), ((1, 1), "duplicated")])
def test_timestamps_out_of_order_or_duplicated_are_refused(tmp_path, swap, word):
    root = make_tum_rgbd(tmp_path / "seq")
    header, entries = [], []
    for line in (root / "rgb.txt").read_text().splitlines():
        (header if line.startswith("#") else entries).append(line)
    first, second = swap
    if first == second:
        entries[first + 1] = entries[first].split()[0] + " " + entries[first + 1].split()[1]
    else:
        entries[first], entries[second] = entries[second], entries[first]
    (root / "rgb.txt").write_text("\n".join(header + entries) + "\n")
    with pytest.raises(InputError, match=rf"rgb\.txt:{len(header) + first + 2}: timestamp .* is {word}"):
        open_sequence(root)


def test_a_listed_image_that_is_missing_is_skipped_and_a_list_of_none_is_refused(tmp_path):
    root = make_tum_rgbd(tmp_path / "seq")
    images = sorted((root / "rgb").iterdir())
    images[2].unlink()
    frames = list(open_sequence(root))
    assert [f.image is None for f in frames] == [False, False, True, False]
    assert frames[2].index == 2 and frames[2].error == f"{images[2]}: no such image file"
    with pytest.raises(InputError, match=rf"{images[2].name}: no such image file"):
        list(open_sequence(root, on_bad_image="abort"))
    for image in images:
        image.unlink(missing_ok=True)
    with pytest.raises(InputError, match=r"rgb\.txt: none of the 4 images it lists exists \(first .*png\)"):
        open_sequence(root)


def test_corrupt_image_is_skipped_or_aborts_by_policy(tmp_path):
    root = make_tum_rgbd(tmp_path / "seq")
    victim = sorted((root / "rgb").iterdir())[2]
    victim.write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    frames = list(open_sequence(root))
    assert [f.image is None for f in frames] == [False, False, True, False]
    assert frames[2].index == 2 and victim.name in frames[2].error and "corrupt" in frames[2].error
    assert frames[2].irradiance is None
    aborting = open_sequence(root, on_bad_image="abort")
    with pytest.raises(InputError, match=rf"{victim.name}: unreadable or corrupt image"):
        list(aborting)
    with pytest.raises(InputError, match=victim.name):
        aborting[2]


def test_image_of_the_wrong_size_is_a_bad_image(tmp_path):
    root = make_tum_rgbd(tmp_path / "seq")
    victim = sorted((root / "rgb").iterdir())[0]
    write_images([victim], 320, 240)
    frame = open_sequence(root)[0]
    assert frame.image is None and "is 320x240, the camera calibration is for 640x480" in frame.error


# --------------------------------------------------------------------------------------------------- EuRoC

T_BS = np.array([[0.0, -1.0, 0.0, 0.1], [1.0, 0.0, 0.0, -0.2], [0.0, 0.0, 1.0, 0.05], [0.0, 0.0, 0.0, 1.0]])

SENSOR_YAML = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [{t_bs}]
rate_hz: 20
resolution: [64, 48]
camera_model: pinhole
intrinsics: [50.0, 51.0, 31.5, 23.5]
distortion_model: {model}
distortion_coefficients: [{coefficients}]
"""


def make_euroc(root: Path, count: int = 3, model="radial-tangential", coefficients="0, 0, 0, 0") -> Path:
    camera_dir = root / "mav0" / "cam0"
    stamps_ns = 1_403_715_273_262_142_976 + np.arange(count, dtype=np.int64) * 50_000_000
    write_images([camera_dir / "data" / f"{ns}.png" for ns in stamps_ns], 64, 48)
    (camera_dir / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{ns},{ns}.png\n" for ns in stamps_ns))
    t_bs = ", ".join(f"{v}" for v in T_BS.ravel())
    (camera_dir / "sensor.yaml").write_text(SENSOR_YAML.format(t_bs=t_bs, model=model, coefficients=coefficients))
    return root


def test_euroc_timestamps_in_seconds_and_ground_truth_converted_to_the_camera(tmp_path):
    root = make_euroc(tmp_path / "V1_01")
    quaternion_z90 = (0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5))  # body rotated 90 degrees about z
    lines = [tum_quaternion_line(t, (1.0, 2.0, 3.0), quaternion_z90) for t in 1403715273.2 + np.arange(30) * 0.005]
    (root / "groundtruth_tum.txt").write_text("\n".join(lines) + "\n")
    sequence = open_sequence(root)
    assert sequence.layout == "euroc" and len(sequence) == 3 and sequence.name == "V1_01"
    np.testing.assert_allclose(sequence.timestamps, 1403715273.262142976 + np.arange(3) * 0.05, atol=1e-6)
    assert isinstance(sequence.raw_camera, RadTanCamera)
    T_world_body = np.eye(4)
    T_world_body[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    T_world_body[:3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_allclose(sequence.ground_truth.poses[0], T_world_body @ T_BS, atol=1e-9)


def test_distorted_images_give_an_irradiance_rectified_in_float(tmp_path):
    frame = open_sequence(make_euroc(tmp_path / "seq", coefficients="-0.28, 0.07, 0.0002, 0.00002"))[0]
    assert frame.irradiance.dtype == np.float32 and frame.irradiance.shape == frame.image.shape
    assert np.any(frame.irradiance != np.round(frame.irradiance))  # not the rounded uint8 image
    assert np.max(np.abs(frame.irradiance - frame.image)) <= 0.5 + 1e-3


def test_euroc_opened_at_mav0_and_native_ground_truth_csv(tmp_path):
    root = make_euroc(tmp_path / "MH_01")
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir()
    rows = [f"{1403715273200000000 + i * 5_000_000},1,2,3,1,0,0,0,0,0,0" for i in range(40)]
    (gt_dir / "data.csv").write_text("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
                                     "q_RS_y [], q_RS_z [], v_x, v_y, v_z\n" + "\n".join(rows) + "\n")
    sequence = open_sequence(root / "mav0")
    assert sequence.name == "MH_01" and len(sequence.ground_truth) == 40
    np.testing.assert_allclose(sequence.ground_truth.poses[0][:3, 3], np.array([1, 2, 3]) + T_BS[:3, 3], atol=1e-9)


def test_euroc_malformed_sensor_yaml_is_refused(tmp_path):
    root = make_euroc(tmp_path / "seq")
    sensor = root / "mav0" / "cam0" / "sensor.yaml"
    sensor.write_text(sensor.read_text().replace("resolution: [64, 48]", "resolution: [64, 48"))
    with pytest.raises(InputError, match=r"sensor\.yaml:\d+: malformed YAML"):
        open_sequence(root)
    sensor.write_text("%YAML:1.0\nintrinsics: [1, 2, 3, 4]\nresolution: [64, 48]\n")
    with pytest.raises(InputError, match=r"sensor\.yaml: missing 'T_BS'"):
        open_sequence(root)


# --------------------------------------------------------------------------------------------------- KITTI


def make_kitti(root: Path, count: int = 3) -> Path:
    write_images([root / "image_0" / f"{i:06d}.png" for i in range(count)], 62, 19)
    (root / "times.txt").write_text("".join(f"{0.1036 * i:.6e}\n" for i in range(count + 5)))
    p0 = "7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {p0}\nP1: {p0}\n")
    (root / "poses").mkdir()
    rows = [np.hstack([np.eye(3), [[0.0], [0.0], [0.8 * i]]]).ravel() for i in range(count + 5)]
    (root / "poses" / "07.txt").write_text("".join(" ".join(f"{v:.6e}" for v in r) + "\n" for r in rows))
    return root


def test_kitti_camera_from_calib_and_poses_by_sequence_number(tmp_path):
    sequence = open_sequence(make_kitti(tmp_path / "kitti07_first3"))
    assert sequence.layout == "kitti" and len(sequence) == 3
    assert sequence.camera == PinholeCamera(62, 19, 718.856, 718.856, 607.1928, 185.2157)
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.1036, 0.2072])
    np.testing.assert_allclose(sequence.ground_truth.positions[:, 2], [0.0, 0.8, 1.6])
    np.testing.assert_allclose(sequence.ground_truth.timestamps, sequence.timestamps)


def test_kitti_colour_camera_uses_p2(tmp_path):
    root = make_kitti(tmp_path / "seq")
    (root / "image_0").rename(root / "image_2")
    p2 = "7.0e+02 0 6.0e+02 4.5e+01 0 7.0e+02 1.8e+02 0 0 0 1 0"
    (root / "calib.txt").write_text((root / "calib.txt").read_text() + f"P2: {p2}\n")
    assert open_sequence(root).camera == PinholeCamera(62, 19, 700.0, 700.0, 600.0, 180.0)


def test_kitti_missing_or_malformed_calibration_is_refused(tmp_path):
    root = make_kitti(tmp_path / "seq")
    (root / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(InputError, match=r"calib\.txt:1: expected 12 numbers, found 3"):
        open_sequence(root)
    (root / "calib.txt").unlink()
    with pytest.raises(InputError, match=r"calib\.txt: calibration not found"):
        open_sequence(root)


# ---------------------------------------------------------------------------------------------------- VAMR


def make_vamr(root: Path, count: int = 3) -> Path:
    write_images([root / "images" / f"img_{i:05d}.png" for i in range(count)], 40, 30)
    (root / "K.txt").write_text("331.37, 0,       20\n0,      369.568, 15\n0,      0,       1\n")
    rows = [f"1 0 0 {0.15 * i:.2f} 0 1 0 0 0 0 1 0 \n" for i in range(count)]
    (root / "poses.txt").write_text("".join(rows))
    return root


def test_vamr_nominal_timestamps_comma_separated_k_and_poses(tmp_path):
    root = make_vamr(tmp_path / "parking")
    sequence = open_sequence(root)
    assert sequence.layout == "vamr" and sequence.camera == PinholeCamera(40, 30, 331.37, 369.568, 20, 15)
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.1, 0.2])
    np.testing.assert_allclose(sequence.ground_truth.positions[:, 0], [0.0, 0.15, 0.30])
    (root / "K.txt").write_text("331.37, 0, 20\n0, 369.568\n0, 0, 1\n")
    with pytest.raises(InputError, match=r"K\.txt:2: expected 3 numbers, found 2"):
        open_sequence(root)


@pytest.mark.parametrize("make, victim", [(make_kitti, "image_0/000001.png"), (make_vamr, "images/img_00001.png")])
def test_an_image_missing_from_the_numbering_is_a_frame_skipped_not_a_frame_less(tmp_path, make, victim):
    root = make(tmp_path / "seq07", count=4)
    (root / victim).unlink()
    sequence = open_sequence(root)
    frames = list(sequence)
    assert [f.index for f in frames] == [0, 1, 2, 3] and [f.image is None for f in frames] == [False, True, False, False]
    assert frames[1].error == f"{root / victim}: no such image file"
    np.testing.assert_allclose(sequence.ground_truth.timestamps, sequence.timestamps)


# -------------------------------------------------------------------------------------- image folder, video

CAMERA_YAML = "model: pinhole\nintrinsics: [40.0, 40.0, 15.5, 11.5]\nresolution: [32, 24]\n"


def test_image_folder_natural_order_and_camera_yaml(tmp_path):
    names = ["frame2.png", "frame10.png", "frame1.png"]
    images = write_images([tmp_path / n for n in names], 32, 24)
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    sequence = open_sequence(tmp_path)
    assert sequence.layout == "image_folder"
    assert [Path(f.path).name for f in sequence] == ["frame1.png", "frame2.png", "frame10.png"]
    assert np.array_equal(sequence[2].image, images[1])
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.1, 0.2])


def test_image_folder_without_camera_or_with_malformed_yaml_is_refused(tmp_path):
    write_images([tmp_path / "a.png"], 32, 24)
    with pytest.raises(InputError, match=r"needs camera\.yaml beside them"):
        open_sequence(tmp_path)
    (tmp_path / "camera.yaml").write_text("model: pinhole\nintrinsics: [40, 40, 15.5, 11.5\n")
    with pytest.raises(InputError, match=r"camera\.yaml:\d+: malformed YAML"):
        open_sequence(tmp_path)
    (tmp_path / "camera.yaml").write_text("model: pinhole\nintrinsics: [40, 40, 15.5]\nresolution: [32, 24]\n")
    with pytest.raises(InputError, match=r"camera\.yaml: camera 'intrinsics' must be 4 numbers"):
        open_sequence(tmp_path)


def test_image_folder_times_file_must_match_the_images(tmp_path):
    write_images([tmp_path / f"{i}.png" for i in range(3)], 32, 24)
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    (tmp_path / "times.txt").write_text("5.0\n5.5\n6.25\n")
    np.testing.assert_allclose(open_sequence(tmp_path).timestamps, [5.0, 5.5, 6.25])
    (tmp_path / "times.txt").write_text("5.0\n5.5\n")
    with pytest.raises(InputError, match=r"times\.txt: 2 timestamps for 3 images"):
        open_sequence(tmp_path)


def test_image_folder_with_images_in_an_images_subfolder_beside_camera_yaml(tmp_path):
    write_images([tmp_path / "images" / f"{i:03d}.png" for i in range(3)], 32, 24)
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    (tmp_path / "vignette.png").write_bytes((tmp_path / "images" / "000.png").read_bytes())  # not a frame
    sequence = open_sequence(tmp_path)
    assert sequence.layout == "image_folder" and sequence.name == tmp_path.name
    assert [Path(f.path).parent.name for f in sequence] == ["images"] * 3
    np.testing.assert_allclose(sequence.timestamps, [0.0, 0.1, 0.2])  # 000.png: a frame number, not a time
    (tmp_path / "times.txt").write_text("5.0\n5.5\n6.25\n")
    np.testing.assert_allclose(open_sequence(tmp_path).timestamps, [5.0, 5.5, 6.25])


def test_image_folder_timestamps_from_names_that_are_times(tmp_path):
    seconds = tmp_path / "seconds"
    # Natural order would put 1341841873.5 before 1341841873.25: names that are times are ordered by time.
    write_images([seconds / f"{name}.png" for name in ("1341841873.5", "1341841873.25", "1341841874.0")], 32, 24)
    (seconds / "camera.yaml").write_text(CAMERA_YAML)
    sequence = open_sequence(seconds)
    np.testing.assert_allclose(sequence.timestamps, [1341841873.25, 1341841873.5, 1341841874.0], rtol=0, atol=1e-6)
    assert [Path(f.path).stem for f in sequence] == ["1341841873.25", "1341841873.5", "1341841874.0"]

    nanoseconds = tmp_path / "nanoseconds"
    stamps = [1403715273262142976, 1403715273312143104]
    write_images([nanoseconds / f"{ns}.png" for ns in stamps], 32, 24)
    (nanoseconds / "camera.yaml").write_text(CAMERA_YAML)
    np.testing.assert_allclose(open_sequence(nanoseconds).timestamps - 1403715273,
                               [0.262142976, 0.312143104], rtol=0, atol=1e-6)

    mixed = tmp_path / "mixed"  # not all times: frame i at i x 0.1 s
    write_images([mixed / f"{name}.png" for name in ("1341841873.5", "preview")], 32, 24)
    (mixed / "camera.yaml").write_text(CAMERA_YAML)
    np.testing.assert_allclose(open_sequence(mixed).timestamps, [0.0, 0.1])


def test_image_folder_names_for_one_time_twice_are_refused(tmp_path):
    write_images([tmp_path / f"{name}.png" for name in ("10.5", "10.50")], 32, 24)
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    with pytest.raises(InputError, match=r"timestamp 10\.5\d* at entry 1 is duplicated"):
        open_sequence(tmp_path)


def test_a_calibration_for_another_resolution_is_refused_naming_both_sizes(tmp_path):
    write_images([tmp_path / f"{i}.png" for i in range(3)], 48, 36)
    (tmp_path / "camera.yaml").write_text(CAMERA_YAML)
    with pytest.raises(InputError, match=r"0\.png: the images are 48x36, but the camera calibration is for 32x24"):
        open_sequence(tmp_path)


def test_a_ground_truth_file_replaces_the_dataset_one(tmp_path):
    write_images([tmp_path / "seq" / f"{i}.png" for i in range(3)], 32, 24)
    (tmp_path / "seq" / "camera.yaml").write_text(CAMERA_YAML)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    (tmp_path / "gt.txt").write_text("".join(" ".join(f"{v}" for v in T[:3].ravel()) + "\n" for T in poses))
    ground_truth = open_sequence(tmp_path / "seq", ground_truth_file=tmp_path / "gt.txt").ground_truth
    np.testing.assert_allclose(ground_truth.timestamps, [0.0, 0.1, 0.2])  # KITTI: the images' times
    np.testing.assert_allclose(ground_truth.poses, poses)
    (tmp_path / "gt.txt").write_text("".join(" ".join(f"{v}" for v in T[:3].ravel()) + "\n" for T in poses[:2]))
    with pytest.raises(InputError, match=r"gt\.txt: 2 poses but 3 timestamps"):
        open_sequence(tmp_path / "seq", ground_truth_file=tmp_path / "gt.txt")


def test_camera_file_option_replaces_the_dataset_calibration(tmp_path):
    root = make_kitti(tmp_path / "seq")
    camera_file = tmp_path / "mine.yaml"
    camera_file.write_text("model: pinhole\nintrinsics: [700, 700, 31, 9]\nresolution: [62, 19]\n")
    assert open_sequence(root, camera_file=camera_file).camera == PinholeCamera(62, 19, 700, 700, 31, 9)
    with pytest.raises(InputError, match=r"nope\.yaml: camera file not found"):
        open_sequence(root, camera_file=tmp_path / "nope.yaml")


def test_video_timestamps_from_the_container_and_backward_reads(tmp_path):
    video = tmp_path / "walk.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (32, 24))
    for i in range(5):
        writer.write(np.full((24, 32, 3), 40 * i, np.uint8))
    writer.release()
    (tmp_path / "walk.yaml").write_text(CAMERA_YAML)
    sequence = open_sequence(video)
    assert sequence.layout == "video" and sequence.name == "walk" and len(sequence) == 5
    np.testing.assert_allclose(sequence.timestamps, np.arange(5) * 0.04, atol=1e-9)
    brightness = [float(f.image.mean()) for f in sequence]
    np.testing.assert_allclose(brightness, np.arange(5) * 40, atol=3)
    assert abs(sequence[1].image.mean() - 40) < 3  # going back reopens the video
    (tmp_path / "walk.yaml").unlink()
    with pytest.raises(InputError, match=r"walk\.avi: a video needs a camera file"):
        open_sequence(video)


# ----------------------------------------------------------------------------------------------- registry


def test_nonexistent_empty_and_unknown_folders_are_refused(tmp_path):
    with pytest.raises(InputError, match=r"missing: no such file or folder"):
        open_sequence(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"empty: the folder is empty"):
        open_sequence(tmp_path / "empty")
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("hello")
    with pytest.raises(InputError, match=r"notes: unknown dataset layout \(looked for: mav0.*rgb\.txt.*K\.txt"):
        open_sequence(tmp_path / "notes")


def test_forced_layout_must_exist_and_match(tmp_path):
    root = make_kitti(tmp_path / "seq")
    assert open_sequence(root, layout="kitti").layout == "kitti"
    with pytest.raises(InputError, match=r"unknown layout 'kitty'"):
        open_sequence(root, layout="kitty")
    with pytest.raises(InputError, match=r"does not look like the tum_rgbd layout"):
        open_sequence(root, layout="tum_rgbd")
    with pytest.raises(InputError, match=r"on_bad_image must be one of skip, abort"):
        open_sequence(root, on_bad_image="ignore")
    assert set(LAYOUTS) == {"euroc", "tum_rgbd", "tum_mono", "kitti", "vamr", "image_folder", "video"}


# ------------------------------------------------------------------------------------------ sequence views


def test_cut_stride_and_reverse_keep_original_indices_and_timestamps(tmp_path):
    root = tmp_path / "folder"
    write_images([root / f"{i:03d}.png" for i in range(10)], 32, 24)
    (root / "camera.yaml").write_text(CAMERA_YAML)
    sequence = open_sequence(root)
    view = sequence.cut(2, 9, stride=3)
    assert [f.index for f in view] == [2, 5, 8] and len(view) == 3 and list(view.indices) == [2, 5, 8]
    np.testing.assert_allclose(view.timestamps, [0.2, 0.5, 0.8])
    backwards = view.reversed()
    assert [f.index for f in backwards] == [8, 5, 2] and backwards[0].index == 8
    assert np.array_equal(backwards[-1].image, sequence[2].image)
    assert [f.index for f in sequence.cut(start=7)] == [7, 8, 9]
    with pytest.raises(InputError, match="leaves none"):
        sequence.cut(5, 5)


def _read_ahead_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "frame-read-ahead" and t.is_alive()]


def test_read_ahead_is_in_order_and_its_thread_stops_with_the_iteration(tmp_path):
    root = tmp_path / "folder"
    write_images([root / f"{i:03d}.png" for i in range(12)], 32, 24)
    (root / "camera.yaml").write_text(CAMERA_YAML)
    ahead = open_sequence(root, read_ahead=2)
    plain = open_sequence(root, read_ahead=0)
    assert [f.index for f in ahead] == list(range(12))
    assert all(np.array_equal(a.image, b.image) for a, b in zip(ahead, plain))
    for frame in ahead:
        if frame.index == 3:
            break
    gc.collect()
    assert _read_ahead_threads() == []


def test_describe_is_json_and_says_what_was_found(tmp_path):
    description = json.loads(json.dumps(open_sequence(make_tum_rgbd(tmp_path / "seq")).describe()))
    assert description["layout"] == "tum_rgbd" and description["frames"] == 4
    assert description["resolution"] == [640, 480]
    assert description["camera"]["intrinsics"] == [535.4, 539.2, 320.1, 247.6]
    assert description["ground_truth"]["poses"] == 40
    assert description["photometric_calibration"] is False


# --------------------------------------------------------------------------------------- bundled sequence


def test_bundled_default_sequence_reads_end_to_end():
    sequence = open_sequence(DEFAULT_SEQUENCE, on_bad_image="abort")
    assert sequence.layout == "tum_rgbd" and len(sequence) == 80
    assert sequence.camera == FR3
    frames = list(sequence)
    assert [f.index for f in frames] == list(range(80))
    assert all(f.image.shape == (480, 640) and f.image.dtype == np.uint8 for f in frames)
    assert (DEFAULT_SEQUENCE / "ATTRIBUTION.md").is_file()
    gt = sequence.ground_truth
    # mocap starts ~0.14 s after the first image (as in the archive) and covers the rest with a margin
    assert gt.timestamps[0] - sequence.timestamps[0] < 0.2 and gt.timestamps[-1] > sequence.timestamps[-1] + 0.4
    assert 280 <= len(gt) <= 320
