"""``fdmo bench MATRIX.yaml``: every cell of a matrix of sequences x methods x settings x tasks x seeds, each as
its own process, on this machine or on Ray, gathered into one table.

    fdmo bench MATRIX.yaml [--workers N] [--ray auto|ADDRESS] [--out DIR] [--retry-failed] [--quiet]

    load the matrix -> skip the cells already in DIR -> run the others (pool or Ray), keeping each row as it comes
    -> results.csv, summary.csv, table.md, ate.png, trajectories.png

The matrix format is in matrix.py, a cell's command and row in cell.py, the pool and Ray in executors.py, the
table and plots in report.py. Each finished cell leaves DIR/cells/<cell>/cell.json: running the same matrix into
the same folder again skips those cells (resume), and ``--retry-failed`` runs again those that failed or timed
out. Ctrl-C (or SIGTERM) stops the cells running (they finish their files), keeps every cell finished, writes the
table of those and exits with 130 (143 for SIGTERM).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import yaml

from app.bench.cell import CELLS_DIR, INTERRUPTED, OK, CellJob
from app.bench.executors import LOCAL_RAY, import_ray, run_in_pool, run_on_ray
from app.bench.matrix import Cell, Matrix, load_matrix
from app.bench.report import write_report
from app.exit_codes import EXIT_INTERRUPTED, EXIT_OK, EXIT_TERMINATED
from app.progress import CellProgress
from vo_core.errors import InputError

CELL_FILE = "cell.json"
MATRIX_FILE = "matrix.yaml"  # the matrix as the bench understood it, beside its results
RESULTS_ROOT = Path("results")

Executor = Callable[[list[CellJob]], Iterator[dict[str, Any]]]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("matrix", type=Path, metavar="MATRIX.yaml", help="the matrix (see configs/bench/)")
    parser.add_argument("--workers", type=_workers, default=default_workers(),
                        help="cells at a time (default: the cores of this machine, %(default)s)")
    parser.add_argument("--ray", metavar="auto|ADDRESS",
                        help="run the cells as Ray tasks: 'auto' starts a local instance (127.0.0.1), ADDRESS joins "
                             "a cluster (Ray is an optional extra: pip install -e \".[cluster]\")")
    parser.add_argument("--out", type=Path, help="results folder; an existing one resumes "
                                                 "(default: results/bench_<matrix>_<time>/)")
    parser.add_argument("--timeout", type=float, help="seconds a cell may run (default: the matrix's timeout_s)")
    parser.add_argument("--retry-failed", action="store_true", help="run again the cells that failed or timed out")
    parser.add_argument("--quiet", action="store_true", help="no progress line, no table")


def default_workers() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _workers(text: str) -> int:
    try:
        workers = int(text)
    except ValueError:
        workers = 0
    if workers < 1:
        raise argparse.ArgumentTypeError(f"--workers {text}: expected a positive integer")
    return workers


def command_bench(args: argparse.Namespace) -> int:
    matrix = load_matrix(args.matrix)
    if args.timeout is not None:
        if args.timeout <= 0:
            raise InputError(f"--timeout {args.timeout:g}: expected a positive number of seconds")
        matrix.timeout_s = args.timeout
    out_dir = args.out or RESULTS_ROOT / f"bench_{args.matrix.stem}_{time.strftime('%Y%m%d-%H%M%S')}"
    if args.ray is not None:
        import_ray(local=args.ray == LOCAL_RAY)  # before anything is written: without Ray, a one-line error

    def executor(jobs: list[CellJob]) -> Iterator[dict[str, Any]]:
        return run_in_pool(jobs, args.workers) if args.ray is None else run_on_ray(jobs, args.ray, args.workers)

    previous = signal.signal(signal.SIGTERM, _interrupt)  # a job scheduler's stop: as Ctrl-C, the cells stopped
    try:
        return bench(matrix, out_dir, executor, retry_failed=args.retry_failed, quiet=args.quiet)
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, stopping the bench as Ctrl-C does, but exiting with its own code."""


def _interrupt(signum, frame) -> None:
    raise _Terminated


def bench(matrix: Matrix, out_dir: Path, executor: Executor, retry_failed: bool = False, quiet: bool = False) -> int:
    """Run the cells of ``matrix`` not yet finished in ``out_dir`` with ``executor`` and write the report over all
    of them. Returns the exit code: 0, or 130 when interrupted, 143 when terminated (the report then covers the
    cells finished)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a folder")
    out_dir = out_dir.absolute()
    (out_dir / CELLS_DIR).mkdir(parents=True, exist_ok=True)
    (out_dir / MATRIX_FILE).write_text(yaml.safe_dump(describe(matrix), sort_keys=False))
    cells = matrix.cells()
    rows = {cell.key: row for cell in cells if (row := finished_row(out_dir, cell, retry_failed)) is not None}
    jobs = [CellJob(cell, str(out_dir / CELLS_DIR / cell.key), matrix.timeout_s) for cell in cells
            if cell.key not in rows]
    say = (lambda text: None) if quiet else (lambda text: print(f"fdmo bench: {text}", file=sys.stderr))
    say(f"{len(cells)} cells, {len(rows)} already done in {out_dir}, {len(jobs)} to run")
    progress = None if quiet else CellProgress(len(jobs))
    stopped_by: KeyboardInterrupt | None = None
    try:
        for row in executor(jobs) if jobs else ():
            if row["status"] == INTERRUPTED:
                continue  # not finished: a resume runs it again
            rows[_key(row)] = row
            (Path(row["folder"]) / CELL_FILE).write_text(json.dumps(row, indent=1) + "\n")
            if progress is not None:
                progress.done(row)
    except KeyboardInterrupt as stop:
        stopped_by = stop
    finally:
        if progress is not None:
            progress.close()
    ordered = [rows[cell.key] for cell in cells if cell.key in rows]
    table = write_report(ordered, {task.name: task.task for task in matrix.tasks}, out_dir) if ordered else ""
    if table and not quiet:
        print(table)
        print(f"results in {out_dir}" + (f" ({len(ordered)} of {len(cells)} cells; run the same command again to "
                                          "go on)" if stopped_by is not None else ""))
    if stopped_by is None:
        return EXIT_OK
    return EXIT_TERMINATED if isinstance(stopped_by, _Terminated) else EXIT_INTERRUPTED


def finished_row(out_dir: Path, cell: Cell, retry_failed: bool) -> dict[str, Any] | None:
    """The row a previous bench left for ``cell`` in ``out_dir`` (None: run it)."""
    path = out_dir / CELLS_DIR / cell.key / CELL_FILE
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None  # never run, cut short, or a file edited by hand: run it
    if retry_failed and row.get("status") != OK:
        return None
    return row


def describe(matrix: Matrix) -> dict[str, Any]:
    return {
        "sequences": [{"name": s.name, "path": s.source, "options": list(s.options), "start": s.start, "end": s.end,
                       "stride": s.stride} for s in matrix.sequences],
        "methods": matrix.methods,
        "seeds": matrix.seeds,
        "settings": {name: list(overrides) for name, overrides in matrix.settings.items()},
        "tasks": [{"name": t.name, "task": t.task, "args": list(t.args)} for t in matrix.tasks],
        "timeout_s": matrix.timeout_s,
    }


def _key(row: dict[str, Any]) -> str:
    return Path(row["folder"]).name

