"""``fdmo experiment timing``: FDMO's Table 2 for this project, the time of each process per method.

    fdmo experiment timing SOURCE [--methods fdmo,direct,klt]

Each method runs once over the whole sequence with a fresh odometry and no sinks (after a throwaway run over
the first frames that loads the compiled kernels). The processes of Table 2, from
the stages each frame's ``FrameResult.timings_ms`` reports (a sample is a frame in which the process ran):

- tracking, per frame: the direct methods' pyramid + coarse tracking + feature-based recovery when it runs (FDMO
  counts its recovery as tracking: "the extra time is reflected in the ... standard deviation"); the KLT
  baseline's KLT + PnP. Immature-point tracing is left out: DSO does it in its mapping thread.
- direct mapping, per keyframe: the direct half's keyframe work (``keyframe``: point activation, window
  optimization, marginalization, new immature points).
- feature mapping, per keyframe: FDMO's feature map grown at a direct keyframe (``feature_mapping``; at
  initialization the initializer's two keyframes in one sample); the KLT baseline's keyframe work
  (triangulation, window bundle adjustment, new corners).
- recovery, per attempt (``recovery``).
- the whole frame (``total``): all of the above done one after the other, as this single-threaded system does.

Writes timings.csv (every frame's stages, per method) and table.md (mean +- standard deviation in ms, and the
number of samples). The sample counts are the same every run; the milliseconds depend on the machine and its load.
"""

from __future__ import annotations

import argparse

import numpy as np

from app.experiments.common import finish, markdown_table, set_up, write_csv
from app.pipeline import track
from vo_core.events import FrameResult
from vo_core.system import IMPLEMENTED_METHODS

NAME = "timing"
HELP = "FDMO Table 2: mean and standard deviation of tracking, mapping and recovery times per method"
TIMINGS_FILE = "timings.csv"
# Table 2's processes: per method, the stage whose presence makes a frame a sample, and the stages summed.
DIRECT_TRACKING = ("track", ("pyramid", "track", "recovery"))
DIRECT_MAPPING = ("keyframe", ("keyframe",))
PROCESSES = {
    "tracking (per frame)": {"fdmo": DIRECT_TRACKING, "direct": DIRECT_TRACKING, "klt": ("klt", ("klt", "pnp"))},
    "direct mapping (per keyframe)": {"fdmo": DIRECT_MAPPING, "direct": DIRECT_MAPPING},
    "feature mapping (per keyframe)": {"fdmo": ("feature_mapping", ("feature_mapping",)),
                                       "klt": ("triangulate", ("triangulate", "ba", "detect"))},
    "recovery (per attempt)": {"fdmo": ("recovery", ("recovery",))},
    "whole frame": {method: ("total", ("total",)) for method in IMPLEMENTED_METHODS},
}
# Each method first tracks this many frames with an odometry that is thrown away: the first call of each compiled
# kernel in a process loads it from numba's cache (half a second on the first frame), which is no part of the time
# the method takes per frame.
WARMUP_FRAMES = 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options beyond the common ones."""


def run(args: argparse.Namespace) -> None:
    setup = set_up(NAME, args, {})
    samples, rows = {}, []
    for method, config in setup.configs.items():
        setup.say(f"{method}: {len(setup.sequence)} frames")
        track(config, setup.sequence.camera, setup.sequence.cut(end=WARMUP_FRAMES))
        results = track(config, setup.sequence.camera, setup.sequence).results
        samples[method] = process_samples(method, results)
        rows += [{"method": method, "frame": result.frame_index, "is_keyframe": result.is_keyframe,
                  **result.timings_ms} for result in results]
    stages = sorted({key for row in rows for key in row} - {"method", "frame", "is_keyframe"})
    write_csv(setup.out_dir / TIMINGS_FILE, [{"method": row["method"], "frame": row["frame"],
                                              "is_keyframe": row["is_keyframe"],
                                              **{stage: row.get(stage) for stage in stages}} for row in rows])
    finish(setup, table(samples))


def process_samples(method: str, results: list[FrameResult]) -> dict[str, list[float]]:
    """The milliseconds of each process of ``PROCESSES`` that ``method`` has, one sample per frame it ran in."""
    samples = {}
    for process, by_method in PROCESSES.items():
        if method in by_method:
            marker, stages = by_method[method]
            samples[process] = [sum(result.timings_ms.get(stage, 0.0) for stage in stages)
                                for result in results if marker in result.timings_ms]
    return samples


def table(samples: dict[str, dict[str, list[float]]]) -> str:
    """Processes down, methods across: mean +- standard deviation (ms) and the number of samples."""
    lines = [(process, *(_cell(by_method.get(process)) for by_method in samples.values())) for process in PROCESSES]
    return markdown_table(("process (ms)", *samples), lines)


def _cell(values: list[float] | None) -> str:
    if values is None:
        return "-"  # the method has no such process
    if not values:
        return "never ran"
    return f"{np.mean(values):.2f} +- {np.std(values):.2f} ({len(values)})"
