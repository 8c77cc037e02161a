"""Initializers of the direct system by name (config key ``direct.initializer``)."""

from __future__ import annotations

from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera
from vo_core.init.base import Initializer

INITIALIZERS = ("coarse",)


def make_initializer(direct_config, init_config, camera: PinholeCamera, seed: int) -> Initializer:
    name = direct_config.initializer
    if name == "coarse":
        from vo_core.direct.coarse_initializer import CoarseInitializer

        c = direct_config
        return CoarseInitializer(
            c.coarse_init, c.selector, c.tracker.huber_threshold, c.immature.outlier_threshold,
            c.point_density, seed,
        )
    raise InputError(f"config key 'direct.initializer': {name!r} is not one of {', '.join(INITIALIZERS)}")
