"""Run one method over the real sequences of ../shared/data and tabulate the results (for BENCHMARKS.md).

    python3 benchmarks/run_shared.py --method direct
    python3 benchmarks/run_shared.py --method klt --config configs/klt/tum.yaml --set klt.window_ba=false

Each folder is run exactly as ``fdmo run FOLDER --method M --no-rrd --quiet`` would (app.pipeline.run_sequence,
the same loaders, configuration and evaluation), its result files kept under --out. Folders that do not exist
are skipped. The Markdown table (sequence, frames, tracked, init frame, ATE m, ms/frame) is printed and written
to <out>/<method>.md. ATE is the RMSE of the camera positions after Sim(3) alignment (vo_core.eval); ms/frame
is the mean wall time of one Odometry.track call.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.pipeline import RunSummary, open_dataset, run_sequence  # noqa: E402
from vo_core.config import METHODS, load_config  # noqa: E402
from vo_core.errors import InputError  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"  # ../shared/data beside the repository
SEQUENCES = ("tum_fr3_teddy_first200", "kitti00_first100", "vamr_parking_first200", "euroc_v101_micro_static")
HEADER = ("sequence", "frames", "tracked", "init frame", "ATE m", "ms/frame")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", choices=METHODS, default="direct")
    parser.add_argument("--data", type=Path, default=SHARED_DATA, help="folder holding the sequences")
    parser.add_argument("--sequences", nargs="+", default=SEQUENCES, help="folder names under --data")
    parser.add_argument("--config", type=Path, help="YAML configuration applied to every sequence")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--end", type=int, help="only the first N frames of each sequence")
    parser.add_argument("--out", type=Path, help="default: results/benchmarks/<method>_<time>")
    args = parser.parse_args()

    config = load_config(args.config, [*args.overrides, f"method={args.method}"])
    out = args.out or Path("results/benchmarks") / f"{args.method}_{time.strftime('%Y%m%d-%H%M%S')}"
    rows = []
    for name in args.sequences:
        folder = args.data / name
        if not folder.is_dir():
            print(f"skipping {folder}: not found", file=sys.stderr)
            continue
        try:
            sequence = open_dataset(folder, config.dataset, end=args.end)
        except InputError as error:
            print(f"skipping {folder}: {error}", file=sys.stderr)
            continue
        print(f"running {args.method} on {name} ({len(sequence)} frames)", file=sys.stderr)
        rows.append(table_row(name, run_sequence(sequence, config, out / name)))
    table = markdown_table(rows)
    print(table)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.method}.md").write_text(table + "\n")
    print(f"written to {out / f'{args.method}.md'}", file=sys.stderr)
    return 0


def table_row(name: str, summary: RunSummary) -> tuple[str, ...]:
    metrics = summary.metrics
    ate = summary.ate_rmse
    step = metrics["timing_ms"].get("step", {}).get("mean")
    return (
        name,
        str(metrics["processed_frames"]),
        f"{metrics['tracked_frames']} ({100 * metrics['tracked_fraction']:.0f}%)",
        "-" if summary.initialization_frame is None else str(summary.initialization_frame),
        "-" if ate is None else f"{ate:.3f}",
        "-" if step is None else f"{step:.0f}",
    )


def markdown_table(rows: list[tuple[str, ...]], header: tuple[str, ...] = HEADER) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
