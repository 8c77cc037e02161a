"""Initializers of the direct system by name (config key ``direct.initializer``).

``auto`` is the feature initializer, and DSO's coarse one for the one attempt after a feature attempt failed (its
own acceptance rules for ``init.max_frames`` frames, or the direct odometry's check after the hand-over): the
feature initializer starts sooner and right where it passes its checks; where it does not, the coarse one sees
the scene another way.

The factory the direct odometry gets (``initializer_factory``) also makes the start check's epipolar witness
(epipolar_check.py), with ``direct.start_check.epipolar``'s settings.
"""

from __future__ import annotations

from dataclasses import dataclass

from vo_core.direct.initialization import Initializer
from vo_core.errors import InputError
from vo_core.geometry.camera import PinholeCamera
from vo_core.init.epipolar_check import EpipolarCheck

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


@dataclass(frozen=True)
class Starts:
    """What the direct odometry gets for its starts (its InitializerFactory, vo_core/direct/initialization.py)."""

    direct_config: object
    init_config: object
    camera: PinholeCamera
    seed: int

    def __call__(self, failed: str | None) -> Initializer:
        return make_initializer(self.direct_config, self.init_config, self.camera, self.seed, failed)

    def start_witness(self) -> EpipolarCheck | None:
        return start_witness(self.direct_config.start_check.epipolar)


def start_witness(config) -> EpipolarCheck | None:
    """A fresh witness for the check of a new start (``direct.start_check.epipolar``'s settings, which the feature
    odometry's starts are checked with too); None where it is disabled."""
    return EpipolarCheck(config) if config.enabled else None


def initializer_factory(direct_config, init_config, camera: PinholeCamera, seed: int) -> Starts:
    """A factory of fresh initializers (and start witnesses) for the direct odometry; an unknown name is refused
    now, not at the first frame."""
    make_initializer(direct_config, init_config, camera, seed)
    return Starts(direct_config, init_config, camera, seed)


def _resolve(configured: str, failed: str | None) -> str:
    if configured != "auto":
        return configured
    return "coarse" if failed == "features" else "features"
