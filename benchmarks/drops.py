"""Forward frame drops (``fdmo run --drop FRAME:COUNT``) on real sequences: the ATE of the whole run, what the
system reported, and the ground-truth motion across the drop, per method and drop size.

    python3 benchmarks/drops.py ../shared/data/tum_fr3_teddy_first200 --at 100 [--counts 5 10 20 30 45 60]
        [--methods fdmo direct] [--set key=value ...]

Each row is one run of the whole sequence with frames AT..AT+COUNT-1 left out (COUNT 0 is the clean run). ATE is
the Sim(3)-aligned RMSE of every posed frame (one alignment for the whole run: a new scale after the drop shows
as a large ATE); "ratio" is that ATE over the clean run's. The motion across the drop is the ground truth's
between the last frame before and the first after (translation m, rotation deg, FDMO 5.3.2's measures). The
events column counts divergence_detected / recovery_succeeded / recovery_failed / direct_resumed / direct_restarted /
reinitialization / reinitialization_abandoned; "posed" is how many of the frames the odometry saw got a pose.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.config import load_config  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.eval.metrics import evaluate, frame_drop_error  # noqa: E402
from vo_core.system import Odometry  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402

REPORTED = ("divergence_detected", "keyframe_overruled", "recovery_succeeded", "recovery_failed", "direct_resumed",
            "direct_restarted", "reinitialization", "reinitialization_abandoned")


def run(sequence, method: str, at: int, count: int, overrides: list[str]) -> tuple[float, int, int, Counter]:
    """(ATE, frames posed, frames seen, event counts) of one run with frames at..at+count-1 left out."""
    odometry = Odometry(load_config(None, [*overrides, f"method={method}"]), sequence.camera)
    stamps, poses, seen, events = [], [], 0, Counter()
    for frame in sequence:
        if at <= frame.index < at + count:
            continue
        seen += 1
        result = odometry.track(frame)
        events.update(event.kind.value for event in result.events)
        if result.T_world_cam is not None:
            stamps.append(frame.timestamp)
            poses.append(result.T_world_cam)
    ate = evaluate(Trajectory(np.array(stamps), np.array(poses)), sequence.ground_truth)["ate"]["rmse"]
    return ate, len(poses), seen, events


def true_motion(sequence, at: int, count: int) -> tuple[float, float]:
    """Ground-truth translation (m) and rotation (deg) between frame at-1 and frame at+count."""
    truth = sequence.ground_truth
    before, after = (np.argmin(np.abs(truth.timestamps - sequence[i].timestamp)) for i in (at - 1, at + count))
    error = frame_drop_error(truth.poses[before], truth.poses[after], truth.poses[before], truth.poses[after])
    return error.true_translation, error.true_rotation_deg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path)
    parser.add_argument("--at", type=int, required=True, help="first frame left out")
    parser.add_argument("--counts", type=int, nargs="+", default=[5, 10, 20, 30, 45, 60])
    parser.add_argument("--methods", nargs="+", default=["fdmo", "direct"])
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    sequence = open_sequence(args.folder)
    print(f"| {args.folder.name} | frames left out | motion | ATE m | ratio | posed/seen | "
          + " / ".join(REPORTED) + " |")
    print("|---|---|---|---|---|---|---|")
    for method in args.methods:
        clean = run(sequence, method, args.at, 0, args.overrides)
        for count in [0, *args.counts]:
            if args.at + count >= len(sequence):
                continue
            ate, posed, seen, events = clean if count == 0 else run(sequence, method, args.at, count, args.overrides)
            motion = "-" if count == 0 else "{:.2f} m, {:.1f} deg".format(*true_motion(sequence, args.at, count))
            counts = " / ".join(str(events[kind]) for kind in REPORTED)
            print(f"| {method} | {args.at}:{count} | {motion} | {ate:.4f} | {ate / clean[0]:.2f} | {posed}/{seen} | "
                  f"{counts} |", flush=True)


if __name__ == "__main__":
    main()
