"""The soak (issue 17; BENCHMARKS.md, "Reliability"): a long run of the synthetic "loop" preset, played round and
round, through the odometry with the Rerun recording on. Does anything grow with the number of frames?

    python3 benchmarks/soak.py                          # 10,000 frames of 320x240 through fdmo
    python3 benchmarks/soak.py --frames 3000 --every 250 --set direct.point_density=1000
    python3 benchmarks/soak.py --rrd-part-frames 0      # the recording in one file, however long

Prints a line per sample (RSS and its peak so far, the maps' sizes, the recording so far), then the RSS drift against
the first sample and the growth of the run's peak (the recording closed) past its value after 1,000 frames (flat:
within 10 % each), the recording's files, its bytes per frame and the frame rate; writes them to <out>/soak.json
beside the run's result files and the recording (recording.rrd, recording.part2.rrd, ...). tests/test_soak.py is
the short version that runs in CI.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.cli import prepare_recording_process  # noqa: E402

if "--no-rrd" not in sys.argv:
    prepare_recording_process()  # as fdmo run does, before rerun loads with app.soak

from app.sinks.recording_parts import PART_FRAMES  # noqa: E402
from app.soak import LOOP_FRAMES, REFERENCE_FRAMES, RSS_TOLERANCE, rss_samples_text, soak  # noqa: E402
from vo_core.config import load_config  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--loop-frames", type=int, default=LOOP_FRAMES, help="frames of one turn of the loop")
    parser.add_argument("--every", type=int, default=500, help="frames between two samples")
    parser.add_argument("--method", default="fdmo")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--no-rrd", action="store_true", help="without the Rerun recording")
    parser.add_argument("--rrd-part-frames", type=int, default=PART_FRAMES,
                        help="frames per file of the recording (0: one file)")
    parser.add_argument("--out", type=Path, help="default: results/benchmarks/soak_<time>")
    args = parser.parse_args()
    out = args.out or Path("results/benchmarks") / f"soak_{time.strftime('%Y%m%d-%H%M%S')}"
    config = load_config(overrides=[f"method={args.method}", *args.overrides])
    started = time.perf_counter()
    report = soak(args.frames, args.width, args.height, out, config, sample_every=args.every,
                  loop_frames=args.loop_frames, recording=not args.no_rrd, part_frames=args.rrd_part_frames)
    wall_s = time.perf_counter() - started
    metrics = report.summary.metrics
    print(rss_samples_text(report))
    growth = "no sample there" if report.peak_growth is None else f"{100 * report.peak_growth:+.1f} %"
    print(f"RSS drift {100 * report.rss_drift:.1f} % of the first sample ({'flat' if report.rss_flat else 'NOT flat'}"
          f"); peak {report.final_peak_mb:.1f} MB, {growth} past its value at frame {REFERENCE_FRAMES} "
          f"({'flat' if report.peak_flat else 'NOT flat'}; tolerance {100 * RSS_TOLERANCE:.0f} %); processed "
          f"{metrics['processed_frames']}, posed {metrics['posed_frames']}; recording "
          f"{report.recording_bytes / 2**20:.1f} MB in {len(report.recording_files)} files, "
          f"{report.bytes_per_frame / 1024:.1f} KiB per frame; {wall_s:.0f} s, "
          f"{metrics['processed_frames'] / wall_s:.1f} frames/s")
    (out / "soak.json").write_text(json.dumps({
        "frames": args.frames, "size": [args.width, args.height], "loop_frames": args.loop_frames,
        "method": args.method, "overrides": args.overrides, "recording": not args.no_rrd,
        "part_frames": args.rrd_part_frames, "recording_files": [path.name for path in report.recording_files],
        "samples": [asdict(sample) for sample in report.samples], "rss_drift": report.rss_drift,
        "rss_flat": report.rss_flat, "final_peak_mb": report.final_peak_mb, "peak_growth": report.peak_growth,
        "peak_flat": report.peak_flat, "recording_bytes": report.recording_bytes,
        "bytes_per_frame": report.bytes_per_frame, "processed_frames": metrics["processed_frames"],
        "posed_frames": metrics["posed_frames"], "wall_s": wall_s}, indent=1) + "\n")
    return 0 if report.rss_flat and report.peak_flat else 1


if __name__ == "__main__":
    sys.exit(main())
