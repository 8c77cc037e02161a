"""Wall time of a stage, in the unit every report uses (FrameResult.timings_ms, the events' "ms")."""

import time


def ms_since(start: float) -> float:
    """Milliseconds since ``start``, a ``time.perf_counter()`` reading."""
    return (time.perf_counter() - start) * 1000.0
