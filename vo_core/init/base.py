"""The interface every initializer of the direct system offers (DSO's CoarseInitializer is the model).

The direct odometry feeds frames until ``track`` returns an ``InitializationResult``; when it has fed
``max_frames`` frames without one it starts over from the current frame. ``status`` says, for the events,
what the latest attempt found (model chosen, tracks kept, why it was rejected).
"""

from __future__ import annotations

from typing import Any, Protocol

from vo_core.direct.pyramid import ImagePyramid
from vo_core.init.result import InitializationResult


class Initializer(Protocol):
    max_frames: int

    @property
    def started(self) -> bool: ...

    def set_first(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> None: ...

    def track(self, frame_index: int, pyramid: ImagePyramid, exposure: float | None) -> InitializationResult | None: ...

    def status(self) -> dict[str, Any]: ...
