"""Student-t fit of photometric residuals and the outlier removal it drives (vo_core/init/photometric_outliers.py)."""

from __future__ import annotations

import numpy as np

from test_direct_support import PlaneScene, pose, small_camera
from vo_core.direct.config import DirectConfig
from vo_core.direct.pixel_selector import PixelSelector
from vo_core.direct.pyramid import ImagePyramid
from vo_core.geometry.lie import se3_inverse
from vo_core.init.config import PhotometricFilterConfig
from vo_core.init.photometric_outliers import photometric_inliers, student_t_scale

CAMERA = small_camera(320, 240)


def test_student_t_scale_is_recovered_from_samples():
    rng = np.random.default_rng(0)
    samples = 3.0 * rng.standard_t(5.0, 20000)
    samples[:500] = rng.uniform(-200, 200, 500)  # gross outliers: the MAD pre-filter drops them
    # The 3-sigma_MAD truncation trims the tails a little: measured 2.81 for a true scale of 3.
    assert abs(student_t_scale(samples, PhotometricFilterConfig()) - 3.0) < 0.3


def test_points_with_wrong_depths_are_removed():
    scene = PlaneScene(seed=3)
    config = DirectConfig()
    poses = [pose((0.0, 0.01 * k, 0.0), (0.04 * k, 0.01 * k, 0.0)) for k in range(4)]
    images = [scene.render(CAMERA, T) for T in poses]
    pyramids = [ImagePyramid(image, CAMERA, config.pyramid) for image, _ in images]
    uv = PixelSelector(config.selector, 0).select(pyramids[0].levels, 800).uv.astype(float)
    depth = images[0][1]
    inverse_depths = 1.0 / depth[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    wrong = np.arange(0, len(uv), 5)
    inverse_depths[wrong] *= 2.0  # far off: the pattern lands on other texture in every other frame
    frames = [(pyramid, se3_inverse(T)) for pyramid, T in zip(pyramids[1:], poses[1:])]
    keep, scales = photometric_inliers(pyramids[0], uv, inverse_depths, frames, PhotometricFilterConfig())
    assert len(scales) == 3 and all(np.isfinite(scales))
    right = np.setdiff1d(np.arange(len(uv)), wrong)
    assert keep[wrong].mean() < 0.2
    assert keep[right].mean() > 0.85  # measured 0.89: patterns across depth edges share the centre depth
