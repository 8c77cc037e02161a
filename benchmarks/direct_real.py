"""The odometry on real sequences: ATE, frames tracked, and time by stage (the configured method; ``--set
method=direct`` for the direct half alone).

    python3 benchmarks/direct_real.py ../shared/data/tum_fr3_teddy_first200 [more folders] [--end N]
        [--set direct.window.enabled=false ...] [--seeds 0 1 2 3 4] [--profile profile.html]

Frames come from the project's loaders (vo_core.datasets.open_sequence) and go straight into the system
(``vo_core.system.Odometry``) without sinks, so the times are the odometry's own. ATE is vo_core.eval's (Sim(3)-aligned
RMSE of the positions that got a pose). Times are split into frames that were only tracked and frames that
became keyframes, per stage (mean / median ms). ``--profile`` writes a pyinstrument HTML profile of the runs.

``--seeds`` runs every folder once per seed (the seed draws the pixel selection's random choices) and adds
the median, minimum and maximum ATE: on these short sequences a small change anywhere moves a single run's
ATE by up to a factor of three (KITTI most), so a comparison of two versions should look at the spread.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.config import load_config  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.eval.metrics import evaluate  # noqa: E402
from vo_core.system import Odometry  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402

# Events counted in a run's line besides the keyframes and tracking failures.
NOTED_EVENTS = ("initialization_rejected", "scale_jump", "reinitialization", "divergence_detected")


def run(folder: Path, overrides: list[str], end: int | None) -> float:
    """One run: prints its line and its stage times; returns its ATE."""
    sequence = open_sequence(folder).cut(end=end)
    return run_sequence(folder.name, sequence, sequence.ground_truth, overrides)


def run_sequence(name: str, sequence, ground_truth, overrides: list[str]) -> float:
    """One run of frames from ``sequence`` (anything that iterates frames and has a ``camera``)."""
    config = load_config(None, overrides)
    odometry = Odometry(config, sequence.camera)
    timestamps, poses, init_frame, failures = [], [], None, 0
    events: dict[str, int] = {}
    stages: dict[bool, dict[str, list[float]]] = {False: {}, True: {}}  # is_keyframe -> stage -> ms
    wall = time.perf_counter()
    for frame in sequence:
        result = odometry.track(frame)
        failures += sum(event.kind.value == "tracking_failed" for event in result.events)
        for event in result.events:
            events[event.kind.value] = events.get(event.kind.value, 0) + 1
        if result.T_world_cam is None:
            continue
        if init_frame is None:
            init_frame = frame.index
        elif "track" in result.timings_ms:
            for stage, ms in result.timings_ms.items():
                stages[result.is_keyframe].setdefault(stage, []).append(ms)
        timestamps.append(frame.timestamp)
        poses.append(result.T_world_cam)
    wall = time.perf_counter() - wall
    ate = float("nan")
    if ground_truth is not None and len(poses) > 2:
        ate = evaluate(Trajectory(np.array(timestamps), np.array(poses)), ground_truth)["ate"]["rmse"]
    noted = ", ".join(f"{events[kind]} {kind}" for kind in NOTED_EVENTS if kind in events)
    print(f"{name}: ATE {ate:.4f} m; tracked {len(poses)}/{len(sequence)}; initialized at frame {init_frame}; "
          f"{events.get('keyframe_added', 0)} keyframes; {failures} tracking failures; "
          f"{len(sequence) / wall:.1f} fps overall{'; ' + noted if noted else ''}")
    for is_keyframe, label in ((False, "tracked-only frames"), (True, "keyframes")):
        by_stage = (f"{stage} {np.mean(ms):.1f}/{np.median(ms):.1f}" for stage, ms in stages[is_keyframe].items())
        print(f"  {label}, ms mean/median: " + ", ".join(by_stage))
    return ate


def run_seeds(folder: Path, overrides: list[str], end: int | None, seeds: list[int]) -> None:
    ates = [run(folder, [*overrides, f"seed={seed}"], end) for seed in seeds]
    print_spread(folder.name, seeds, ates)


def print_spread(name: str, seeds: list[int], ates: list[float]) -> None:
    print(f"{name}: ATE over seeds {seeds}: median {np.median(ates):.4f}, min {np.min(ates):.4f}, "
          f"max {np.max(ates):.4f} m; each {', '.join(f'{ate:.4f}' for ate in ates)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--end", type=int, default=None, help="only the first N frames")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--seeds", type=int, nargs="+", help="one run per seed, and the ATE's spread")
    parser.add_argument("--profile", type=Path, help="write a pyinstrument HTML profile here")
    args = parser.parse_args()
    profiler = None
    if args.profile:
        from pyinstrument import Profiler

        profiler = Profiler(interval=0.0005)
    with profiler or contextlib.nullcontext():
        for folder in args.folders:
            if args.seeds:
                run_seeds(folder, args.overrides, args.end, args.seeds)
            else:
                run(folder, args.overrides, args.end)
    if profiler:
        args.profile.write_text(profiler.output_html())
        print(profiler.output_text(unicode=False, color=False, show_all=False)[:6000])


if __name__ == "__main__":
    main()
