"""The odometry on the synthetic presets: Sim(3)-aligned ATE, frames tracked, initialization, failures.

    python3 benchmarks/direct_synthetic.py [--presets smooth forward ...] [--frames 60] [--size 640x480]
        [--set direct.window.enabled=false ...]

Each preset is rendered by vo_core.synthetic (seed 0 unless --seed) and tracked by the system
(vo_core.system.Odometry) with the default configuration and method (``--set method=direct`` for the direct half
alone, or other --set overrides); the estimate is evaluated by vo_core.eval.evaluate against the rendered ground
truth.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.config import load_config  # noqa: E402
from vo_core.eval.metrics import evaluate  # noqa: E402
from vo_core.synthetic import PRESETS, make_sequence  # noqa: E402
from vo_core.system import Odometry  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402


def run(preset: str, frames: int, width: int, height: int, seed: int, overrides: list[str]) -> None:
    sequence = make_sequence(preset, frames, seed, width, height)
    config = load_config(None, [f"seed={seed}", *overrides])
    odometry = Odometry(config, sequence.camera)
    stamps, poses, failures, init_frame, track_ms = [], [], 0, None, []
    start = time.perf_counter()
    for frame in sequence:
        result = odometry.track(frame)
        failures += sum(e.kind.value == "tracking_failed" for e in result.events)
        if "track" in result.timings_ms:
            track_ms.append(result.timings_ms["track"])
        if result.T_world_cam is not None:
            init_frame = frame.index if init_frame is None else init_frame
            stamps.append(frame.timestamp)
            poses.append(result.T_world_cam)
    wall = time.perf_counter() - start
    if len(poses) < 3:
        print(f"{preset}: tracked {len(poses)}/{len(sequence)}; {failures} tracking failures")
        return
    metrics = evaluate(Trajectory(np.array(stamps), np.array(poses)), sequence.ground_truth)
    truth = sequence.ground_truth.positions
    path = float(np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1)))
    print(
        f"{preset}: ATE {metrics['ate']['rmse']:.4f} m (path {path:.2f} m); tracked {len(poses)}/{len(sequence)}; "
        f"initialized at frame {init_frame}; {failures} tracking failures; "
        f"track {np.median(track_ms) if track_ms else float('nan'):.1f} ms median; {len(sequence) / wall:.1f} fps"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=[p for p in PRESETS if p != "static"], choices=PRESETS)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--size", default="640x480", help="WxH")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    for preset in args.presets:
        run(preset, args.frames, width, height, args.seed, args.overrides)


if __name__ == "__main__":
    main()
