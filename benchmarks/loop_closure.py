"""Loop closure on a rendered circuit played twice round: fdmo with loop closure off, then on.

    python benchmarks/loop_closure.py [FRAMES_PER_ROUND] [SEED]     (defaults 180, 1)

The "circuit" preset turns once round a circle facing outwards, so the second round sees the first again from the
same places. Prints, for each setting, every closed loop, the ATE of the whole run and of the first round, and how far
apart the estimate puts the same place seen a round apart (the poses tracking gave, moved by the loops' corrections
as trajectory.tum is).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from app.experiments.two_loop import estimated_trajectory
from vo_core.config import load_config
from vo_core.eval.metrics import evaluate
from vo_core.events import EventKind
from vo_core.geometry.lie import so3_geodesic_angle
from vo_core.synthetic import make_sequence
from vo_core.synthetic.faults import looping
from vo_core.system import Odometry
from vo_core.trajectory import Trajectory

WIDTH, HEIGHT = 320, 240


def ground_truth_apart(played, loop_details: dict) -> tuple[float, float]:
    """(degrees, metres) between the loop's two keyframes by ground truth: one place is within ~15 deg and 0.2 m."""
    truth = dict(zip(played.indices.tolist(), played.ground_truth.poses))
    here, there = truth[loop_details["keyframe"]], truth[loop_details["loop_keyframe"]]
    return (float(np.degrees(so3_geodesic_angle(here[:3, :3], there[:3, :3]))),
            float(np.linalg.norm(here[:3, 3] - there[:3, 3])))


def run(played, camera, loop_closure: bool) -> tuple[np.ndarray, np.ndarray, list]:
    """(timestamps, corrected poses, LOOP_CLOSED events) of one run."""
    odometry = Odometry(load_config(overrides=[f"features.loop_closing.enabled={str(loop_closure).lower()}"]), camera)
    results = [odometry.track(frame) for frame in played]
    odometry.close()
    estimate = estimated_trajectory(results)
    loops = [e for r in results for e in r.events if e.kind is EventKind.LOOP_CLOSED]
    return estimate.timestamps, estimate.poses, loops


def main() -> None:
    frames = int(sys.argv[1]) if len(sys.argv) > 1 else 180
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    sequence = make_sequence("circuit", frames, seed=seed, width=WIDTH, height=HEIGHT)
    played = looping(sequence, 2 * frames)
    truth = played.ground_truth
    for loop_closure in (False, True):
        start = time.perf_counter()
        times, poses, loops = run(played, sequence.camera, loop_closure)
        for loop in loops:
            degrees, metres = ground_truth_apart(played, loop.details)
            print(f"  loop: keyframe {loop.details['keyframe']} -> {loop.details['loop_keyframe']}, "
                  f"scale {loop.details['scale']}, {loop.details['moved_keyframes']} keyframes moved, "
                  f"{degrees:.1f} deg and {metres:.3f} m apart by ground truth")
        first = int(np.searchsorted(played.timestamps, times[0]))
        by_time = dict(zip(times.tolist(), poses))
        a, b = by_time.get(played.timestamps[first]), by_time.get(played.timestamps[first + frames])
        gap = np.nan if a is None or b is None else np.linalg.norm(b[:3, 3] - a[:3, 3])
        round_one = times < played.timestamps[frames]
        ate = evaluate(Trajectory(times, poses), truth)["ate"]["rmse"]
        ate_one = evaluate(Trajectory(times[round_one], poses[round_one]), truth)["ate"]["rmse"]
        print(f"loop closure {'on' if loop_closure else 'off'}: {len(times)} of {len(played)} posed, ATE {ate:.4f}, "
              f"first round {ate_one:.4f}, the same place a round apart {1000 * gap:.1f} mm apart "
              f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
