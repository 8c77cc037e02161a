"""Time per frame of the direct odometry by stage, over repeated runs, with an optional pyinstrument profile.

    python3 benchmarks/direct_profile.py ../shared/data/tum_fr3_teddy_first200 [--end N] [--repeats 3]
        [--clock cpu] [--set direct.window.enabled=false ...] [--pyinstrument profile.html] [--save poses.npz]

Frames are read once into memory, the first frames are run once untimed (numba loads its cached kernels on
first use), then the sequence is run ``--repeats`` times with a fresh ``Odometry`` (the configured method's
direct half is timed).
Each stage's time of each frame is the median over the repeats (the machine is shared: the median rejects the
runs a neighbour slowed down), then summarized over frames as mean / median / 90th percentile, for frames that
were only tracked and for frames that became keyframes, separately. The stages:

    pyramid      ImagePyramid of the frame
    track        all motion hypotheses tried (``hypotheses``: how many, ``residual_evals``: calcRes calls)
    trace        epipolar tracing of the immature points of every window keyframe
    slide        choosing the keyframes that leave the window
    marginalize  marginalizing them (their information becomes the window's prior)
    activate     activation of converged immature points (distance map + inverse-depth optimization)
    window       the windowed photometric bundle adjustment
    select       pixel selection on the new keyframe
    reference    the new tracking reference (window points projected into the keyframe, per-level arrays)
    rest         the remainder of the keyframe (immature points' creation, bookkeeping)
    other        with --clock cpu, a tracked-only frame's time in ``track`` and ``accept`` besides track and trace

Stage times come from wrapping the odometry's methods on the instance (nothing in vo_core changes); frames
that fed the initializer are left out. ``--clock wall`` (default) reads the odometry's own wall-clock timings
for pyramid, track and trace; ``--clock cpu`` times every stage by the process's CPU time instead, which a
busy shared machine inflates far less (pyramid is then the frame's time outside ``track`` and ``accept``). The script also reports ATE, frames tracked, and whether the repeats
gave the same trajectory (the odometry is deterministic: they must). ``--save`` writes the poses of the first
run so that two versions of the code can be compared frame by frame (``--compare`` reads such a file).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.config import load_config  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.eval.metrics import evaluate  # noqa: E402
from vo_core.system import Odometry  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402

# Methods timed as stages (attribute path on the system's DirectOdometry instance -> stage).
TRACK_STAGES = {"track": "tracking", "accept": "tracking", "_best_hypothesis": "track", "_trace": "trace"}  # cpu
KEYFRAME_STAGES = {
    "_slide_window": "slide",  # older odometry: choice and marginalization in one method
    "_keyframes_to_marginalize": "slide",
    "_marginalize": "marginalize",
    "_activate_points": "activate",
    "_optimize_window": "window",
    "selector.select": "select",
    "_set_tracking_reference": "reference",
}
FRAME_STAGES = ("pyramid", "track", "trace")
WARM_UP_FRAMES = 20  # an untimed first pass: loading numba's cached kernels takes a while on first use


class StageClock:
    """Per-frame stage times (ms) and counters, filled by wrappers around the odometry's methods."""

    def __init__(self, clock=time.perf_counter):
        self.clock = clock
        self.current: dict[str, float] = defaultdict(float)

    def timed(self, owner, name: str, stage: str) -> None:
        method = getattr(owner, name)

        @functools.wraps(method)
        def wrapper(*args, **kwargs):
            start = self.clock()
            try:
                return method(*args, **kwargs)
            finally:
                self.current[stage] += (self.clock() - start) * 1000.0

        setattr(owner, name, wrapper)

    def counted(self, owner, name: str, counter: str) -> None:
        method = getattr(owner, name)

        @functools.wraps(method)
        def wrapper(*args, **kwargs):
            self.current[counter] += 1
            return method(*args, **kwargs)

        setattr(owner, name, wrapper)

    def take(self) -> dict[str, float]:
        out, self.current = dict(self.current), defaultdict(float)
        return out


def instrumented_odometry(config, camera, cpu: bool) -> tuple[Odometry, StageClock]:
    odometry = Odometry(config, camera)
    direct = odometry.direct
    clock = StageClock(time.process_time if cpu else time.perf_counter)
    stages = {**KEYFRAME_STAGES, **(TRACK_STAGES if cpu else {})}
    for path, stage in stages.items():
        *parents, name = path.split(".")
        owner = functools.reduce(getattr, parents, direct)
        if hasattr(owner, name):  # the odometry evolves: a stage it no longer has is simply not reported
            clock.timed(owner, name, stage)
    if cpu:
        clock.timed(odometry, "track", "total")
    clock.counted(direct.tracker, "track", "hypotheses")
    clock.counted(direct.tracker, "_residuals", "residual_evals")
    return odometry, clock


def run_once(frames, camera, config, cpu: bool) -> tuple[list[dict[str, float] | None], list[np.ndarray | None]]:
    """One pass: per frame its stage times (None while initializing) and its pose (None if untracked)."""
    odometry, clock = instrumented_odometry(config, camera, cpu)
    records, poses = [], []
    for frame in frames:
        result = odometry.track(frame)
        stages = clock.take()
        poses.append(None if result.T_world_cam is None else result.T_world_cam.copy())
        if "track" not in result.timings_ms:
            records.append(None)
            continue
        named = sum(stages.get(stage, 0.0) for stage in KEYFRAME_STAGES.values())
        if cpu:
            tracking = stages.pop("tracking")  # track + trace + keyframe
            stages["pyramid"] = stages["total"] - tracking
            remainder = tracking - stages.get("track", 0.0) - stages.get("trace", 0.0)
            stages["keyframe" if result.is_keyframe else "other"] = remainder
        else:
            stages.update({stage: result.timings_ms.get(stage, 0.0) for stage in (*FRAME_STAGES, "total")})
            stages["keyframe"] = result.timings_ms.get("keyframe", 0.0)
        if result.is_keyframe:
            stages["rest"] = stages["keyframe"] - named
        stages["is_keyframe"] = float(result.is_keyframe)
        records.append(stages)
    return records, poses


def median_over_repeats(runs: list[list[dict | None]]) -> list[dict | None]:
    """Per frame and stage, the median over the repeats (all repeats share the keyframe decisions)."""
    merged = []
    for per_frame in zip(*runs):
        if per_frame[0] is None:
            merged.append(None)
            continue
        keys = set().union(*(record.keys() for record in per_frame))
        merged.append({key: float(np.median([record.get(key, 0.0) for record in per_frame])) for key in keys})
    return merged


def summarize(records: list[dict | None]) -> None:
    keyframe_stages = dict.fromkeys(KEYFRAME_STAGES.values())  # unique, in order
    order = ("pyramid", "track", "trace", "other", *keyframe_stages, "rest", "keyframe", "total", "hypotheses",
             "residual_evals")
    for is_keyframe, title in ((0.0, "tracked-only frames"), (1.0, "keyframes")):
        rows = [r for r in records if r is not None and r["is_keyframe"] == is_keyframe]
        print(f"  {title} ({len(rows)}): mean / median / p90")
        for stage in order:
            values = [r.get(stage, 0.0) for r in rows]
            if not rows or not any(values):
                continue
            unit = "" if stage in ("hypotheses", "residual_evals") else " ms"
            summary = np.mean(values), np.median(values), np.percentile(values, 90)
            print(f"    {stage:15s}" + "".join(f"{value:8.2f}" for value in summary) + unit)


def pose_difference(poses_a: list, poses_b: list) -> float:
    """Largest position difference between two runs' poses of the same frames (inf if tracked differently)."""
    worst = 0.0
    for a, b in zip(poses_a, poses_b):
        if (a is None) != (b is None):
            return float("inf")
        if a is not None:
            worst = max(worst, float(np.linalg.norm(a[:3, 3] - b[:3, 3])))
    return worst


def report_accuracy(sequence, frames, poses) -> None:
    tracked = [(frame.timestamp, pose) for frame, pose in zip(frames, poses) if pose is not None]
    ate = float("nan")
    if sequence.ground_truth is not None and len(tracked) > 2:
        timestamps, matrices = zip(*tracked)
        trajectory = Trajectory(np.array(timestamps), np.array(matrices))
        ate = evaluate(trajectory, sequence.ground_truth)["ate"]["rmse"]
    print(f"{sequence.root.name}: ATE {ate:.4f} m; tracked {len(tracked)}/{len(frames)}")


def profile_sequence(folder: Path, args) -> None:
    config = load_config(None, args.overrides)
    if config.method == "klt":
        raise SystemExit("direct_profile.py times the direct methods; --set method=direct or fdmo")
    sequence = open_sequence(folder).cut(end=args.end)
    frames = list(sequence)
    run_once(frames[:WARM_UP_FRAMES], sequence.camera, config, args.clock == "cpu")  # loads the compiled kernels
    runs, first_poses = [], None
    for repeat in range(args.repeats):
        records, poses = run_once(frames, sequence.camera, config, args.clock == "cpu")
        runs.append(records)
        if first_poses is None:
            first_poses = poses
        else:
            difference = pose_difference(first_poses, poses)
            print(f"  repeat {repeat}: largest position difference to the first run {difference:.3g}")
    report_accuracy(sequence, frames, first_poses)
    summarize(median_over_repeats(runs))
    if args.save:
        np.savez(args.save, **{str(f.index): p for f, p in zip(frames, first_poses) if p is not None})
    if args.compare:
        stored = np.load(args.compare)
        other = [stored[str(f.index)] if str(f.index) in stored else None for f in frames]
        print(f"  largest position difference to {args.compare}: {pose_difference(first_poses, other):.3g}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--end", type=int, default=None, help="only the first N frames")
    parser.add_argument("--repeats", type=int, default=3, help="runs per sequence; stage times are their median")
    parser.add_argument("--clock", choices=("wall", "cpu"), default="wall", help="wall-clock or process CPU time")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--pyinstrument", type=Path, help="write a pyinstrument HTML profile of all runs here")
    parser.add_argument("--save", type=Path, help="write the first run's poses (npz, one entry per frame index)")
    parser.add_argument("--compare", type=Path, help="compare the first run's poses with a --save file")
    args = parser.parse_args()
    if (args.save or args.compare) and len(args.folders) > 1:
        parser.error("--save and --compare take one folder")
    profiler = None
    if args.pyinstrument:
        from pyinstrument import Profiler

        profiler = Profiler(interval=0.0005)
    with profiler or contextlib.nullcontext():
        for folder in args.folders:
            profile_sequence(folder, args)
    if profiler:
        args.pyinstrument.write_text(profiler.output_html())
        print(profiler.output_text(unicode=False, color=False, show_all=False)[:8000])


if __name__ == "__main__":
    main()
