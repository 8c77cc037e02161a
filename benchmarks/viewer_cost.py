"""What the viewers cost the tracking thread: milliseconds per frame spent in each sink's methods.

    python3 benchmarks/viewer_cost.py [SEQUENCE] [--method direct] [--end N]

Runs the sequence as ``fdmo run`` does (app.pipeline.run_sequence) with the Rerun sink and the viser page
attached, each wrapped so that every call into it is timed on the tracking thread: wall time and the thread's
CPU time (time.thread_time, which leaves out the viewers' own background threads and other processes). Prints
per sink the mean and the 95th percentile over frames, and the size of the recording.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.pipeline import open_dataset, run_sequence  # noqa: E402
from app.player import Player  # noqa: E402
from app.sinks.rerun_sink import RerunSink  # noqa: E402
from app.sinks.viser_view import ViserView  # noqa: E402
from vo_core.config import METHODS, load_config  # noqa: E402
from vo_core.datasets import DEFAULT_SEQUENCE  # noqa: E402


class TimedSink:
    """Forwards the Sink calls to ``sink`` and adds up their wall and thread CPU time per frame."""

    def __init__(self, sink):
        self.sink = sink
        self.wall_ms: dict[int, float] = defaultdict(float)
        self.cpu_ms: dict[int, float] = defaultdict(float)
        self._frame = -1

    def _timed(self, method, *arguments) -> None:
        wall, cpu = time.perf_counter(), time.thread_time()
        method(*arguments)
        self.wall_ms[self._frame] += 1000.0 * (time.perf_counter() - wall)
        self.cpu_ms[self._frame] += 1000.0 * (time.thread_time() - cpu)

    def on_frame(self, frame, result) -> None:
        self._frame = result.frame_index
        self._timed(self.sink.on_frame, frame, result)

    def on_event(self, event) -> None:
        self._timed(self.sink.on_event, event)

    def on_map(self, snapshot) -> None:
        self._timed(self.sink.on_map, snapshot)

    def close(self) -> None:
        self.sink.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", nargs="?", default=DEFAULT_SEQUENCE)
    parser.add_argument("--method", choices=METHODS, default="direct")
    parser.add_argument("--end", type=int)
    parser.add_argument("--port", type=int, default=8093)
    args = parser.parse_args()
    config = load_config(None, [f"method={args.method}"])
    sequence = open_dataset(args.sequence, config.dataset, end=args.end)
    player = Player(sequence)
    with tempfile.TemporaryDirectory() as out:
        recording = Path(out) / "recording.rrd"
        rerun = TimedSink(RerunSink(str(recording), sequence.camera, sequence.ground_truth))
        viser = TimedSink(ViserView(sequence.camera, player, sequence.ground_truth, port=args.port))
        summary = run_sequence(sequence, config, Path(out) / "run", [rerun, viser], player=player)
        size_mb = recording.stat().st_size / 1e6
    print(f"{sequence.name}: {summary.metrics['processed_frames']} frames, {args.method}, "
          f"odometry step {summary.metrics['timing_ms']['step']['mean']:.1f} ms/frame (viewers included)")
    print("| sink | wall ms/frame (mean, p95) | thread CPU ms/frame (mean, p95) |\n|---|---|---|")
    for name, sink in (("RerunSink", rerun), ("ViserView", viser)):
        wall, cpu = np.array(list(sink.wall_ms.values())), np.array(list(sink.cpu_ms.values()))
        print(f"| {name} | {wall.mean():.2f}, {np.percentile(wall, 95):.2f} | "
              f"{cpu.mean():.2f}, {np.percentile(cpu, 95):.2f} |")
    print(f"recording: {size_mb:.1f} MB ({1000 * size_mb / len(sequence):.0f} kB/frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
