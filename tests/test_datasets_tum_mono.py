"""TUM monoVO layout and DSO's camera.txt on tiny generated folders: relative FOV intrinsics, DSO's crop size,
exposure times and photometric correction, images.zip, NaN rows of groundtruthSync.txt."""

from __future__ import annotations

import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from vo_core.datasets import open_sequence
from vo_core.datasets.calibration import read_dso_camera
from vo_core.errors import InputError
from vo_core.geometry.camera import EquidistantCamera, FovCamera, PinholeCamera, RadTanCamera

WIDTH, HEIGHT = 64, 48
EXPOSURES_MS = (10.0, 20.0, 10.0)
GRAY = 128
VIGNETTE_FALLOFF = 0.3  # V = 1 - 0.3 r^2, r = 1 at half the image width from the centre


def inverse_response(pixel):
    return 255.0 * (pixel / 255.0) ** 1.5


def make_tum_mono(root: Path, zipped: bool = False) -> Path:
    root.mkdir(parents=True)
    rng = np.random.default_rng(3)
    image = cv2.resize(rng.integers(20, 200, (6, 8), dtype=np.uint8), (WIDTH, HEIGHT), interpolation=cv2.INTER_LINEAR)
    # frames 0 and 1 show the same scene at two exposures; frame 2 is a uniform gray
    images = [image, image, np.full_like(image, GRAY)]
    if zipped:
        with zipfile.ZipFile(root / "images.zip", "w") as archive:
            for i, im in enumerate(images):
                archive.writestr(f"{i:05d}.png", cv2.imencode(".png", im)[1].tobytes())
    else:
        (root / "images").mkdir()
        for i, im in enumerate(images):
            cv2.imwrite(str(root / "images" / f"{i:05d}.png"), im)
    times = [f"{i:05d} {1000.0 + 0.05 * i:.6f} {exposure}\n" for i, exposure in enumerate(EXPOSURES_MS)]
    (root / "times.txt").write_text("".join(times))
    (root / "camera.txt").write_text(f"0.5 0.625 0.5 0.5 0.9\n{WIDTH} {HEIGHT}\ncrop\n32 24\n")
    (root / "pcalib.txt").write_text(" ".join(f"{inverse_response(i):.6f}" for i in range(256)) + "\n")
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    radius2 = ((u - WIDTH / 2) ** 2 + (v - HEIGHT / 2) ** 2) / (WIDTH / 2) ** 2
    vignette = (1.0 - VIGNETTE_FALLOFF * radius2).clip(0.1, 1)
    cv2.imwrite(str(root / "vignette.png"), (65535 * vignette).astype(np.uint16))
    no_pose = " ".join(["nan"] * 7)
    (root / "groundtruthSync.txt").write_text(
        f"1000.000000 0 0 0 0 0 0 1\n1000.050000 {no_pose}\n1000.100000 1 0 0 0 0 0 1\n"
    )
    return root


def test_tum_mono_calibration_exposures_and_ground_truth(tmp_path):
    sequence = open_sequence(make_tum_mono(tmp_path / "sequence_01"))
    assert sequence.layout == "tum_mono" and len(sequence) == 3
    # relative intrinsics: fx * w, fy * h, cx * w - 0.5, cy * h - 0.5 (DSO's pixel-corner to pixel-centre)
    assert sequence.raw_camera == FovCamera(WIDTH, HEIGHT, 32.0, 30.0, 31.5, 23.5, 0.9)
    assert (sequence.camera.width, sequence.camera.height) == (32, 24)  # DSO's "crop" to camera.txt's size
    np.testing.assert_allclose(sequence.timestamps, [1000.0, 1000.05, 1000.1])
    assert [f.exposure_ms for f in sequence] == list(EXPOSURES_MS)
    np.testing.assert_allclose(sequence.ground_truth.timestamps, [1000.0, 1000.1])  # the NaN line is dropped
    assert sequence.describe()["photometric_calibration"] is True


def test_tum_mono_irradiance_is_corrected_for_response_and_vignette(tmp_path):
    sequence = open_sequence(make_tum_mono(tmp_path / "seq"))
    uniform = sequence[2].irradiance
    assert uniform.dtype == np.float32 and uniform.shape == (24, 32)
    # G^-1(128) at the centre, where V is ~1; larger towards the corners, where the vignette darkened the image
    np.testing.assert_allclose(uniform[11:13, 15:17], inverse_response(GRAY), rtol=0.01)
    assert uniform[0, 0] > 1.05 * uniform[12, 16]
    # the exposure is not divided out (DSO): it goes with the frame to the affine brightness model
    short, long = sequence[0], sequence[1]
    assert (short.exposure_ms, long.exposure_ms) == (10.0, 20.0)
    np.testing.assert_array_equal(short.irradiance, long.irradiance)


def test_tum_mono_images_zip_gives_the_same_frames(tmp_path):
    folder = open_sequence(make_tum_mono(tmp_path / "folder"))
    zipped = open_sequence(make_tum_mono(tmp_path / "zipped", zipped=True))
    assert zipped.layout == "tum_mono" and len(zipped) == 3
    assert zipped[2].path.endswith("images.zip:00002.png")
    assert all(np.array_equal(a.image, b.image) for a, b in zip(folder, zipped))


def test_tum_mono_times_not_matching_the_images_is_refused(tmp_path):
    root = make_tum_mono(tmp_path / "seq")
    (root / "times.txt").write_text("00000 1000.0 10\n00001 1000.05 10\n")
    with pytest.raises(InputError, match=r"times\.txt: 2 lines for 3 images"):
        open_sequence(root)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("Pinhole 400 410 319.5 239.5 0\n640 480\n", PinholeCamera(640, 480, 400, 410, 319.5, 239.5)),
        ("400 410 319.5 239.5 0\n640 480\n", PinholeCamera(640, 480, 400, 410, 319.5, 239.5)),
        (
            "RadTan 400 410 319.5 239.5 -0.2 0.05 0.001 0.002\n640 480\n",
            RadTanCamera(640, 480, 400, 410, 319.5, 239.5, -0.2, 0.05, 0.001, 0.002),
        ),
        (
            "EquiDistant 300 300 319.5 239.5 0.01 -0.02 0.003 -0.001\n640 480\nfull\n640 480\n",
            EquidistantCamera(640, 480, 300, 300, 319.5, 239.5, 0.01, -0.02, 0.003, -0.001),
        ),
    ],
)
def test_dso_camera_file_models(tmp_path, text, expected):
    (tmp_path / "camera.txt").write_text(text)
    calibration = read_dso_camera(tmp_path / "camera.txt")
    assert calibration.camera == expected and calibration.output is None


def test_dso_camera_file_output_line_gives_the_rectified_camera(tmp_path):
    root = make_tum_mono(tmp_path / "seq")
    (root / "camera.txt").write_text(f"FOV 0.5 0.625 0.5 0.5 0.9\n{WIDTH} {HEIGHT}\n0.4 0.5 0.5 0.5 0\n32 24\n")
    assert open_sequence(root).camera == PinholeCamera(32, 24, 12.8, 12.0, 15.5, 11.5)
    assert open_sequence(root, undistort_output="none").camera == PinholeCamera(WIDTH, HEIGHT, 32, 30, 31.5, 23.5)


@pytest.mark.parametrize(
    "text, message",
    [
        ("Ortho 1 2 3 4 5\n640 480\n", r"camera\.txt:1: unknown camera model 'Ortho'"),
        ("400 410 319.5\n640 480\n", r"camera\.txt:1: expected 5 \(FOV/pinhole\) or 8 \(RadTan\) numbers"),
        ("FOV 400 410 319.5 239.5 x\n640 480\n", r"camera\.txt:1: not a number"),
        ("FOV 400 410 319.5 239.5 0.9\n", r"camera\.txt: a DSO camera file needs at least 2 lines"),
        ("FOV 400 410 319.5 239.5 0.9\n640.5 480\n", r"camera\.txt:2: image size must be two positive integers"),
    ],
)
def test_malformed_dso_camera_file_is_refused(tmp_path, text, message):
    (tmp_path / "camera.txt").write_text(text)
    with pytest.raises(InputError, match=message):
        read_dso_camera(tmp_path / "camera.txt")
