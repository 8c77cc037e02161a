"""One cell of ``fdmo bench``: a command of this tool run as its own process, and the row it gives.

A cell is exactly what a user would type (``fdmo run SOURCE --method M --set seed=S ...``, or ``fdmo experiment
two-loop ...``), run with this interpreter in the cell's folder, its output in log.txt; the row is read back
from the files the command writes (metrics.json, trials.csv, loops.csv). A process of its own keeps a crash, a
leak or a hang inside the cell: a non-zero exit becomes a failed row with the command's one-line error, a cell
past its timeout is stopped and reported, and the others go on.

``run_cell`` is the task both executors run (a thread of the process pool, a Ray task on any node): it takes a
``CellJob`` (plain, picklable) and returns a row (a plain dict).
"""

from __future__ import annotations

import csv
import json
import math
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from app.bench.matrix import Cell
from app.exit_codes import INTERRUPTED_CODES

CELLS_DIR = "cells"
LOG_FILE = "log.txt"
OK, FAILED, TIMEOUT, INTERRUPTED = "ok", "failed", "timeout", "interrupted"
ERROR_PREFIX = "fdmo: error: "  # app/cli.py's one-line message on bad input
STOP_GRACE_S = 10.0  # after SIGINT, how long a cell may take to write its files before it is killed
# The columns of a row, in the order of results.csv. The metrics are those of the cell's task; others stay empty.
LABELS = ("sequence", "method", "setting", "task", "seed")
METRICS = ("ate_m", "rpe_m", "rpe_deg", "tracked_fraction", "initialization_frame", "fps", "keyframes", "failures",
           "recoveries", "reinitializations", "forward_limit_frames", "backward_limit_frames", "alignment_error_m",
           "scale_drift", "rotation_drift_deg")
COLUMNS = (*LABELS, "status", "error", *METRICS, "wall_s", "folder", "command")
TIMING_COLUMNS = ("fps", "wall_s")
# A cell is one CPU's work (a Ray task asks for one): the thread pools of OpenCV, BLAS and numba kept to one thread,
# so that N workers never run more threads than N cores and a cell's fps does not depend on how many run beside it.
ONE_THREAD = {name: "1" for name in ("OPENCV_FOR_THREADS_NUM", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                     "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}  # what changes from one machine, or one load, to the next


@dataclass(frozen=True)
class CellJob:
    cell: Cell
    folder: str  # absolute: where the cell writes (on a cluster, a path every node shares)
    timeout_s: float


def command(cell: Cell, folder: Path, python: str = sys.executable) -> list[str]:
    """The command line of ``cell``, writing into ``folder``, run by ``python`` (the interpreter of the process
    that runs the cell: on a cluster, the node's)."""
    sequence = cell.sequence
    cut = [*(["--start", str(sequence.start)] if sequence.start is not None else []),
           *(["--end", str(sequence.end)] if sequence.end is not None else [])]
    stride = ["--stride", str(sequence.stride)] if sequence.stride != 1 else []
    settings = [item for override in (*cell.overrides, f"seed={cell.seed}") for item in ("--set", override)]
    if cell.task.task == "run":
        head = ["run", sequence.source, "--method", cell.method, "--no-rrd", *cut, *stride]
    else:  # the matrix refuses a start or an end with the experiments
        head = ["experiment", cell.task.task, sequence.source, "--methods", cell.method, *stride]
    return [python, "-m", "app", *head, *sequence.options, *settings, "--out", str(folder), "--quiet",
            *cell.task.args]


def run_cell(job: CellJob) -> dict[str, Any]:
    """Run the cell's command to its end, its timeout or a stop (``stop_running_cells``); the row it gives."""
    folder = Path(job.folder)
    folder.mkdir(parents=True, exist_ok=True)
    argv = command(job.cell, folder)
    started = time.perf_counter()
    with (folder / LOG_FILE).open("w") as log:
        log.write(shlex.join(argv) + "\n")
        log.flush()
        process = subprocess.Popen(argv, cwd=folder, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   env={**os.environ, **ONE_THREAD},
                                   start_new_session=True)  # Ctrl-C reaches the bench, which stops the cells
        with _RUNNING_LOCK:
            _RUNNING.add(process)
        try:
            status, error = _wait(process, job.timeout_s, folder)
        except KeyboardInterrupt:  # a Ray task cancelled: its cell must not run on, orphaned
            _stop(process)
            raise
        finally:
            with _RUNNING_LOCK:
                _RUNNING.discard(process)
    row = {**job.cell.labels(), "status": status, "error": error, **dict.fromkeys(METRICS),
           "wall_s": time.perf_counter() - started, "folder": str(folder), "command": shlex.join(argv)}
    if status == OK:
        try:
            row.update(read_metrics(job.cell.task.task, folder))
        except (OSError, ValueError, KeyError) as problem:
            row.update(status=FAILED, error=f"the command's results do not parse: {problem}")
    return row


def _wait(process: subprocess.Popen, timeout_s: float, folder: Path) -> tuple[str, str | None]:
    try:
        code = process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        _stop(process)
        return TIMEOUT, f"still running after {timeout_s:g} s: stopped"
    if code == 0:
        return OK, None
    if code in INTERRUPTED_CODES or code == -signal.SIGINT:
        return INTERRUPTED, "stopped before its end"
    if code < 0:
        return FAILED, f"killed by {signal.Signals(-code).name}"
    return FAILED, _last_line(folder / LOG_FILE) or f"exit code {code}"


def _stop(process: subprocess.Popen) -> None:
    """SIGINT first, so that the command finishes its files, then SIGKILL."""
    process.send_signal(signal.SIGINT)
    try:
        process.wait(timeout=STOP_GRACE_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


_RUNNING: set[subprocess.Popen] = set()
_RUNNING_LOCK = threading.Lock()


def stop_running_cells() -> None:
    """Stop every cell this process is running (Ctrl-C on the bench: the cells run in sessions of their own, so
    the terminal's signal does not reach them)."""
    with _RUNNING_LOCK:
        running = list(_RUNNING)
    for process in running:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)


def _last_line(log: Path) -> str | None:
    """The command's one-line error (fdmo's contract on bad input), or the last line of a traceback."""
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1].removeprefix(ERROR_PREFIX) if len(lines) > 1 else None  # the first line is the command


# ------------------------------------------------------------------------------------------------ reading back


def read_metrics(task: str, folder: Path) -> dict[str, Any]:
    return {"run": _run_metrics, "frame-drop": _frame_drop_metrics, "two-loop": _two_loop_metrics}[task](folder)


def _run_metrics(folder: Path) -> dict[str, Any]:
    """metrics.json of ``fdmo run``."""
    metrics = json.loads((folder / "metrics.json").read_text())
    evaluation = metrics.get("evaluation") or {}
    rpe = evaluation.get("rpe", {})
    events = metrics["events"]
    return {
        "ate_m": evaluation.get("ate", {}).get("rmse"),
        "rpe_m": rpe.get("translation", {}).get("rmse"),
        "rpe_deg": rpe.get("rotation_deg", {}).get("rmse"),
        "tracked_fraction": metrics["tracked_fraction"],
        "initialization_frame": metrics["initialization_frame"],
        "fps": metrics["fps"],
        "keyframes": metrics["keyframes"],
        "failures": events.get("tracking_failed", 0) + events.get("divergence_detected", 0),
        "recoveries": events.get("recovery_succeeded", 0),
        "reinitializations": events.get("reinitialization", 0),
    }


def _frame_drop_metrics(folder: Path) -> dict[str, Any]:
    """trials.csv of ``fdmo experiment frame-drop``: per direction, the largest jump survived (frames), the
    smallest over the jump frames when there are several."""
    trials = _csv_rows(folder / "trials.csv")
    limits: dict[str, dict[str, int]] = {}
    for trial in trials:
        survived = int(trial["frames"]) if trial["survived"] == "1" else 0
        at_limits = limits.setdefault(trial["direction"], {})
        at_limits[trial["at_frame"]] = max(at_limits.get(trial["at_frame"], 0), survived)
    return {f"{direction}_limit_frames": min(limits[direction].values()) if direction in limits else None
            for direction in ("forward", "backward")}


def _two_loop_metrics(folder: Path) -> dict[str, Any]:
    """loops.csv of ``fdmo experiment two-loop``: the drifts at the end of the second loop."""
    last = _csv_rows(folder / "loops.csv")[-1]
    return {
        "ate_m": _number(last["ate_m"]),
        "tracked_fraction": int(last["posed_frames"]) / max(int(last["frames"]), 1),
        "alignment_error_m": _number(last["alignment_error_m"]),
        "scale_drift": _number(last["scale_drift"]),
        "rotation_drift_deg": _number(last["rotation_drift_deg"]),
        "failures": int(last["tracking_failures"]) + int(last["divergences"]),
        "recoveries": int(last["recoveries"]),
        "reinitializations": int(last["reinitializations"]),
    }


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as file:
        rows = list(csv.DictReader(file))
    if not rows:
        raise ValueError(f"{path.name} has no rows")
    return rows


def _number(text: str) -> float | None:
    value = float(text) if text else None
    return None if value is None or math.isnan(value) else value
