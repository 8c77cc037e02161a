"""Initializers of the direct system by name (config key ``direct.initializer``)."""

from __future__ import annotations

from vo_core.direct.initialization import Initializer, InitializerFactory
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera

INITIALIZERS = ("coarse", "features")


def make_initializer(direct_config, init_config, camera: PinholeCamera, seed: int) -> Initializer:
    name = direct_config.initializer
    if name == "coarse":
        from vo_core.direct.coarse_initializer import CoarseInitializer

        c = direct_config
        return CoarseInitializer(
            c.coarse_init, c.selector, c.tracker.huber_threshold, c.immature.outlier_threshold,
            c.point_density, seed,
        )
    if name == "features":
        from vo_core.init.config import InitConfig
        from vo_core.init.feature_initializer import FeatureInitializer

        config = init_config if init_config is not None else InitConfig()
        return FeatureInitializer(config, direct_config, camera, seed)
    raise InputError(f"config key 'direct.initializer': {name!r} is not one of {', '.join(INITIALIZERS)}")


def initializer_factory(direct_config, init_config, camera: PinholeCamera, seed: int) -> InitializerFactory:
    """A factory of fresh initializers for the direct odometry; an unknown name is refused now, not at the
    first frame."""
    make_initializer(direct_config, init_config, camera, seed)
    return lambda: make_initializer(direct_config, init_config, camera, seed)
