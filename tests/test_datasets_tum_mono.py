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


def make_tum_mono(root: Path, zipped: bool = False) -> Path:
    root.mkdir(parents=True)
    rng = np.random.default_rng(3)
    image = cv2.resize(rng.integers(20, 200, (6, 8), dtype=np.uint8), (WIDTH, HEIGHT), interpolation=cv2.INTER_LINEAR)
    # frames 0 and 1 show the same scene; 2 is a different one
    images = [image, image, 255 - image]
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
    (root / "pcalib.txt").write_text(" ".join(f"{255.0 * (i / 255.0) ** 1.5:.6f}" for i in range(256)) + "\n")
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    radius2 = ((u - WIDTH / 2) ** 2 + (v - HEIGHT / 2) ** 2) / (WIDTH / 2) ** 2
    cv2.imwrite(str(root / "vignette.png"), (65535 * (1.0 - 0.3 * radius2).clip(0.1, 1)).astype(np.uint16))
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


def test_tum_mono_irradiance_is_corrected_for_exposure_and_response(tmp_path):
    sequence = open_sequence(make_tum_mono(tmp_path / "seq"))
    short, long = sequence[0], sequence[1]  # the same scene at 10 ms and 20 ms
    assert short.irradiance.dtype == np.float32 and short.irradiance.shape == (24, 32)
    valid = short.irradiance > 1e-3
    np.testing.assert_allclose(long.irradiance[valid] / short.irradiance[valid], 0.5, rtol=1e-4)
    assert not np.allclose(short.irradiance, short.image.astype(np.float32))


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
    assert calibration.camera == expected and calibration.output_size is None


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
