"""Initializers of the direct system by name (config key ``direct.initializer``).

``auto`` is the feature initializer, and DSO's coarse one for the one attempt after a feature attempt failed (its
own acceptance rules for ``init.max_frames`` frames, or the direct odometry's check after the hand-over): the
feature initializer starts sooner and right where it passes its checks; where it does not, the coarse one sees
the scene another way.
"""

from __future__ import annotations

from vo_core.direct.initialization import Initializer, InitializerFactory
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera

INITIALIZERS = ("coarse", "features", "auto")


def make_initializer(direct_config, init_config, camera: PinholeCamera, seed: int,
                     failed: str | None = None) -> Initializer:
    """The configured initializer for an attempt after the attempt of initializer ``failed`` (None: after a
    success, or the first)."""
    name = _resolve(direct_config.initializer, failed)
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
    return lambda failed: make_initializer(direct_config, init_config, camera, seed, failed)


def _resolve(configured: str, failed: str | None) -> str:
    if configured != "auto":
        return configured
    return "coarse" if failed == "features" else "features"
