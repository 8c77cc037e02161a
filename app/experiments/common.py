"""What the experiments share: the source and the methods' configurations, frames fed to a fresh odometry, the
ground truth at the frames, and the results folder with its files and table.

Every experiment feeds ``vo_core.system.Odometry`` the frames it chooses, in the order it chooses (the Player is
not involved), one fresh odometry per run: the odometry draws every random choice from generators seeded with
``config.seed``, so a run fed the same frames gives the same poses, and an experiment run twice the same numbers.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from app.pipeline import check_method, open_source
from vo_core.config import Config, DatasetConfig, dump_config, load_config
from vo_core.errors import InputError
from vo_core.eval import DEFAULT_MAX_DT_S, associate_timestamps
from vo_core.events import EventKind, FrameResult
from vo_core.system import IMPLEMENTED_METHODS

DEFAULT_METHODS = ("fdmo", "direct", "klt")
RESULTS_ROOT = Path("results")
TABLE_FILE = "table.md"
# The events a trial or a loop reports, by the column that counts them.
EVENT_COLUMNS = {
    "tracking_failures": EventKind.TRACKING_FAILED,
    "divergences": EventKind.DIVERGENCE_DETECTED,
    "recoveries": EventKind.RECOVERY_SUCCEEDED,
    "failed_recoveries": EventKind.RECOVERY_FAILED,
    "reinitializations": EventKind.REINITIALIZATION,
    "reinitializations_abandoned": EventKind.REINITIALIZATION_ABANDONED,
    "loops_closed": EventKind.LOOP_CLOSED,  # with loop closure on
    "maps_merged": EventKind.MAPS_MERGED,
}


def methods(text: str) -> tuple[str, ...]:
    """``--methods fdmo,direct,klt``: implemented methods, each once, in the order given."""
    names = tuple(dict.fromkeys(name.strip() for name in text.split(",") if name.strip()))
    unknown = [name for name in names if name not in IMPLEMENTED_METHODS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(
            f"--methods {text}: expected a comma-separated list of {', '.join(IMPLEMENTED_METHODS)}")
    return names


def add_common_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="SOURCE",
                        help="dataset folder, or synthetic:PRESET[:FRAMES[:WIDTHxHEIGHT]] (vo_core.synthetic)")
    parser.add_argument("--methods", type=methods, default=DEFAULT_METHODS,
                        help=f"comma-separated methods (default: {','.join(DEFAULT_METHODS)})")
    parser.add_argument("--out", type=Path, help="results folder (default: results/<experiment>_<sequence>_<time>/)")
    parser.add_argument("--config", type=Path, help="YAML configuration for every method (its method key is ignored)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one setting for every method (repeatable)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


@dataclass
class Setup:
    """An experiment about to run: its sequence, one configuration per method, and its results folder."""

    name: str
    sequence: Any  # vo_core.datasets.Sequence or vo_core.synthetic.SyntheticSequence
    configs: dict[str, Config]
    out_dir: Path
    quiet: bool

    def say(self, text: str) -> None:
        if not self.quiet:
            print(f"fdmo experiment {self.name}: {text}", file=sys.stderr, flush=True)


def set_up(name: str, args: argparse.Namespace, settings: dict[str, Any]) -> Setup:
    """Open the source, resolve each method's configuration (refusing a method that cannot run on this camera
    before anything is written), and write them with the experiment's ``settings`` into the results folder."""
    configs = {method: load_config(args.config, [*args.overrides, f"method={method}"]) for method in args.methods}
    first = next(iter(configs.values()))
    sequence = open_source(args.source, first.dataset, args.layout, args.camera, ground_truth_file=args.gt,
                           stride=args.stride)
    for config in configs.values():
        check_method(config, sequence.camera)
    out_dir = args.out or RESULTS_ROOT / f"{name}_{sequence.name}_{time.strftime('%Y%m%d-%H%M%S')}"
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a folder")
    out_dir.mkdir(parents=True, exist_ok=True)
    for method, config in configs.items():
        dump_config(config, out_dir / f"config_{method}.yaml")
    described = {"experiment": name, "source": args.source, "sequence": sequence.name, "stride": args.stride,
                 "frames": len(sequence),
                 "methods": list(configs), **settings}
    (out_dir / "experiment.yaml").write_text(yaml.safe_dump(described, sort_keys=False))
    return Setup(name, sequence, configs, out_dir, args.quiet)


def truth_at_frames(sequence) -> dict[int, np.ndarray]:
    """The ground-truth T_world_cam of each frame, by position in the sequence: the pose nearest in time within
    the association tolerance of TUM's associate.py; frames without one are left out (TUM monoVO's middle)."""
    ground_truth = sequence.ground_truth
    if ground_truth is None:
        raise InputError(f"{sequence.name}: no ground truth, and the experiment compares with it (--gt FILE)")
    matches = associate_timestamps(sequence.timestamps, ground_truth.timestamps, DEFAULT_MAX_DT_S)
    return {int(position): ground_truth.poses[row] for position, row in zip(matches.first, matches.second)}


def frame_interval(sequence) -> float:
    """The sequence's usual time between two frames (s)."""
    return float(np.median(np.diff(sequence.timestamps))) if len(sequence) > 1 else 0.0


def relabelled(frame, index: int, timestamp: float):
    """The frame under another number and time: the odometry keys keyframes by frame number, and frames played
    again or after a jump must not reuse the numbers and times of frames it has already seen."""
    return dataclasses.replace(frame, index=index, timestamp=timestamp)


def count_events(results: Iterable[FrameResult]) -> dict[str, int]:
    """The EVENT_COLUMNS counts of the events of ``results``."""
    kinds = [event.kind for result in results for event in result.events]
    return {column: kinds.count(kind) for column, kind in EVENT_COLUMNS.items()}


def write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rows with the same keys as CSV; floats with 6 significant digits, None and NaN as empty fields."""
    with path.open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]) if rows else [])
        writer.writeheader()
        writer.writerows({key: _csv_value(value) for key, value in row.items()} for row in rows)


def _csv_value(value: Any) -> Any:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.6g}"
    return "" if value is None else value


def markdown_table(header: Iterable[str], rows: Iterable[Iterable[Any]]) -> str:
    lines = [list(header)]
    lines.append(["---"] * len(lines[0]))
    lines.extend([str(cell) for cell in row] for row in rows)
    return "\n".join("| " + " | ".join(line) + " |" for line in lines)


def finish(setup: Setup, table: str) -> None:
    """Write the table beside the raw results and print it."""
    (setup.out_dir / TABLE_FILE).write_text(table + "\n")
    print(table)
    print(f"results in {setup.out_dir}")


def figure(width: float, height: float):
    """A matplotlib Figure without pyplot (no global state, no display; PNG through Agg), as app/plot.py draws."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")
