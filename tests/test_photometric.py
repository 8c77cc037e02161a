"""Photometric calibration: inverse response, vignette, exposure; TUM monoVO files and their errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vo_core.errors import InputError
from vo_core.geometry.camera import RadTanCamera
from vo_core.geometry.photometric import PhotometricCalibration, load_photometric_calibration
from vo_core.geometry.undistorter import Undistorter

WIDTH, HEIGHT = 64, 48
GAMMA = 2.2


def gamma_inverse_response(scale: float = 1000.0) -> np.ndarray:
    """G^-1 of a gamma camera, in arbitrary units (pcalib files are not normalized)."""
    return scale * (np.arange(256) / 255.0) ** GAMMA


def vignette_at(u: np.ndarray, v: np.ndarray, falloff: float = 0.5) -> np.ndarray:
    """A radial falloff from 1 at the image centre to 1 - falloff at the corners."""
    r2 = (u - WIDTH / 2) ** 2 + (v - HEIGHT / 2) ** 2
    return 1.0 - falloff * r2 / ((WIDTH / 2) ** 2 + (HEIGHT / 2) ** 2)


def radial_vignette(falloff: float = 0.5) -> np.ndarray:
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    return vignette_at(u, v, falloff).astype(np.float32)


def image_of(irradiance: np.ndarray, vignette: np.ndarray, exposure_ms: float) -> np.ndarray:
    """The forward model I = G(t V B) of a gamma camera (Engel et al. 2016, eq. 1), quantized to 8 bits."""
    energy = exposure_ms * vignette * irradiance  # in units where G(255 (x / 255)^gamma) = x
    return np.clip(np.round(255.0 * (energy / 255.0) ** (1.0 / GAMMA)), 0, 255).astype(np.uint8)


def test_identity_returns_the_image_as_float32():
    image = np.random.default_rng(0).integers(0, 256, (HEIGHT, WIDTH), dtype=np.uint8)
    calibration = PhotometricCalibration.identity()
    assert calibration.is_identity
    corrected = calibration.correct(image)
    assert corrected.dtype == np.float32
    np.testing.assert_array_equal(corrected, image)
    np.testing.assert_allclose(calibration.correct(image, exposure_ms=4.0), image / 4.0, rtol=1e-6)


def test_linear_response_in_any_units_is_the_identity():
    image = np.arange(256, dtype=np.uint8).reshape(16, 16)
    calibration = PhotometricCalibration(inverse_response=7.0 + 3.5 * np.arange(256))
    assert not calibration.is_identity
    np.testing.assert_allclose(calibration.correct(image), image, atol=1e-4)


def test_gamma_response_is_linearized():
    calibration = PhotometricCalibration(inverse_response=gamma_inverse_response())
    image = np.array([[0, 64, 128, 255]], dtype=np.uint8)
    np.testing.assert_allclose(calibration.correct(image), 255.0 * (image / 255.0) ** GAMMA, rtol=1e-5)


def test_energies_agree_across_exposures_and_vignetting():
    """The same scene seen at two exposure times through a vignetted lens: the corrected energies match."""
    rng = np.random.default_rng(1)
    irradiance = rng.uniform(2.0, 12.0, (HEIGHT, WIDTH))
    vignette = radial_vignette()
    calibration = PhotometricCalibration(gamma_inverse_response(), vignette)
    short, long = 5.0, 18.0
    energy_short = calibration.correct(image_of(irradiance, vignette, short), exposure_ms=short)
    energy_long = calibration.correct(image_of(irradiance, vignette, long), exposure_ms=long)
    # Each energy is the irradiance, up to 8-bit quantization (a few percent in the darkest pixels).
    np.testing.assert_allclose(energy_long, irradiance, rtol=0.03)
    np.testing.assert_allclose(energy_short, irradiance, rtol=0.08)
    # Without the calibration the two images differ by far more than that.
    raw_ratio = image_of(irradiance, vignette, long).astype(float) / image_of(irradiance, vignette, short)
    assert raw_ratio.mean() > 1.5


def test_vignette_is_divided_out():
    vignette = radial_vignette()
    image = np.full((HEIGHT, WIDTH), 100, np.uint8)
    corrected = PhotometricCalibration(vignette=vignette).correct(image)
    np.testing.assert_allclose(corrected, 100.0 / vignette, rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"inverse_response": np.arange(255.0)}, "expected 256 values of the inverse response, found 255"),
        ({"inverse_response": np.r_[np.arange(100.0), 98.0, np.arange(101.0, 256.0)]}, "strictly increasing"),
        ({"vignette": np.zeros((4, 4))}, r"vignette values must lie in \(0, 1\]"),
        ({"vignette": np.full((4, 4), 1.5)}, r"vignette values must lie in \(0, 1\]"),
        ({"vignette": np.ones((4, 4, 3))}, "single-channel"),
    ],
)
def test_invalid_arrays_are_refused(kwargs, message):
    with pytest.raises(InputError, match=message):
        PhotometricCalibration(**kwargs)


def test_correct_refuses_mismatched_input():
    calibration = PhotometricCalibration(vignette=radial_vignette())
    with pytest.raises(ValueError, match="does not match the vignette"):
        calibration.correct(np.zeros((HEIGHT + 1, WIDTH), np.uint8))
    with pytest.raises(ValueError, match="2-D uint8"):
        calibration.correct(np.zeros((HEIGHT, WIDTH), np.float32))
    with pytest.raises(ValueError, match="exposure time must be positive"):
        calibration.correct(np.zeros((HEIGHT, WIDTH), np.uint8), exposure_ms=0.0)


# ----------------------------------------------------------------------------------------------- files


def write_pcalib(path, values) -> None:
    path.write_text(" ".join(f"{v:.6f}" for v in values) + "\n")


@pytest.mark.parametrize("dtype,peak", [(np.uint8, 255), (np.uint16, 65535)])
def test_load_tum_monovo_files(tmp_path, dtype, peak):
    write_pcalib(tmp_path / "pcalib.txt", gamma_inverse_response())
    vignette = radial_vignette()
    stored = np.round(vignette * peak * 0.9).astype(dtype)  # not normalized on disk: the brightest pixel is 0.9
    cv2.imwrite(str(tmp_path / "vignette.png"), stored)
    calibration = load_photometric_calibration(tmp_path / "pcalib.txt", tmp_path / "vignette.png", (WIDTH, HEIGHT))
    assert calibration.vignette.max() == 1.0
    np.testing.assert_allclose(calibration.vignette, vignette, atol=2.0 / (0.9 * peak))
    image = np.full((HEIGHT, WIDTH), 128, np.uint8)
    expected = 255.0 * (128 / 255.0) ** GAMMA / calibration.vignette
    np.testing.assert_allclose(calibration.correct(image), expected, rtol=1e-4)


def test_either_file_may_be_absent(tmp_path):
    write_pcalib(tmp_path / "pcalib.txt", gamma_inverse_response())
    only_response = load_photometric_calibration(tmp_path / "pcalib.txt", None)
    assert only_response.vignette is None and only_response.inverse_response is not None
    assert load_photometric_calibration(None, None).is_identity


def test_pcalib_over_several_lines_is_accepted(tmp_path):
    values = gamma_inverse_response()
    (tmp_path / "pcalib.txt").write_text("\n".join(" ".join(map(str, row)) for row in values.reshape(16, 16)))
    np.testing.assert_allclose(
        load_photometric_calibration(tmp_path / "pcalib.txt", None).inverse_response,
        PhotometricCalibration(values).inverse_response,
    )


@pytest.mark.parametrize(
    "content,message",
    [
        (" ".join(map(str, range(200))), "expected 256 values of the inverse response, found 200"),
        (" ".join(map(str, list(range(255)) + [3])), "strictly increasing, but value 255 \\(3\\)"),
        (" ".join(map(str, range(255))) + " abc", "must be numbers"),
        ("", "found 0"),
    ],
)
def test_malformed_pcalib_names_the_file(tmp_path, content, message):
    path = tmp_path / "pcalib.txt"
    path.write_text(content)
    with pytest.raises(InputError, match=f"^{path}: .*{message}"):
        load_photometric_calibration(path, None)


def vignette_error(tmp_path, write) -> str:
    path = tmp_path / "vignette.png"
    write(path)
    with pytest.raises(InputError) as error:
        load_photometric_calibration(None, path, (WIDTH, HEIGHT))
    message = str(error.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    return message


def test_malformed_vignettes_name_the_file(tmp_path):
    def png(array):
        return lambda path: cv2.imwrite(str(path), array)

    assert "is 32x48 but the images are 64x48" in vignette_error(tmp_path, png(np.full((48, 32), 200, np.uint8)))
    with_zero = np.full((HEIGHT, WIDTH), 200, np.uint8)
    with_zero[0, 0] = 0
    assert "1 zero pixels" in vignette_error(tmp_path, png(with_zero))
    colour = np.full((HEIGHT, WIDTH, 3), 200, np.uint8)
    assert "single-channel" in vignette_error(tmp_path, png(colour))
    assert "cannot decode" in vignette_error(tmp_path, lambda path: path.write_bytes(b"\x89PNG not really"))
    with pytest.raises(InputError, match="vignette image not found"):
        load_photometric_calibration(None, tmp_path / "missing.png")
    with pytest.raises(InputError, match="photometric calibration file not found"):
        load_photometric_calibration(tmp_path / "missing.txt", None)


def test_vignette_rectifies_like_an_image():
    """The vignette is given in the raw geometry; the undistorter maps it to the pinhole view as any float image."""
    camera = RadTanCamera(WIDTH, HEIGHT, 50.0, 50.0, 31.5, 23.5, -0.2, 0.05, 0.0, 0.0)
    undistorter = Undistorter(camera, "crop")
    rectified = undistorter.rectify(radial_vignette())
    assert rectified.dtype == np.float32 and rectified.shape == (HEIGHT, WIDTH)
    # Each rectified pixel holds the vignette of the raw pixel it sees.
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    target_uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    raw_uv = camera.project(undistorter.camera.unproject(target_uv))
    expected = vignette_at(raw_uv[:, 0], raw_uv[:, 1]).reshape(HEIGHT, WIDTH)
    np.testing.assert_allclose(rectified, expected, atol=2e-3)
