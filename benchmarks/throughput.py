"""Whole-process throughput: fdmo runs and a peer system's, timed in turn on the same machine (issue 18).

    python3 benchmarks/throughput.py ../shared/data/tum_fr3_teddy_first200 --runs 3 \
        --contender fdmo="--no-rrd" --contender recorded="" --contender direct="--method direct --no-rrd" \
        --peer dso="../peers/dso/run_dso_native.sh {folder} {trajectory}"

Each contender is one whole process as a user starts it: ``fdmo run FOLDER --quiet --out DIR`` with the
contender's arguments (the Rerun recording is on unless they say ``--no-rrd``), or a peer's command line with
``{folder}`` and ``{trajectory}`` (the TUM file it must write) filled in (build the peers as ../shared/peers/README.md
says, and let them read the folder's own image files, as fdmo does: a peer fed images converted beforehand skips
their decoding, BENCHMARKS.md, Real time, tenth stop). Round after round every contender runs once, in the
same order, so a slow spell of the machine touches them all. Per contender: median wall time, CPU time (user + sys)
and peak RSS of the process and its children (os.wait4), keyframes (fdmo) and ATE (the Sim(3)-aligned RMSE of the
posed frames against the folder's ground truth, vo_core.eval, for peers too). Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.pipeline import open_dataset  # noqa: E402
from benchmarks.run_shared import markdown_table  # noqa: E402
from vo_core.config import DatasetConfig  # noqa: E402
from vo_core.eval import evaluate  # noqa: E402
from vo_core.trajectory import read_trajectory  # noqa: E402

HEADER = ("contender", "runs", "wall s (median, range)", "CPU s", "peak RSS MB", "keyframes", "ATE m (median)")


@dataclass
class Contender:
    name: str
    arguments: str  # fdmo run's extra arguments, or the peer's command line
    peer: bool
    runs: list[dict] = field(default_factory=list)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--contender", action="append", default=[], metavar="NAME=ARGS",
                        help="an fdmo run with these arguments (default: fdmo=\"--no-rrd\")")
    parser.add_argument("--peer", action="append", default=[], metavar="NAME=COMMAND")
    parser.add_argument("--out", type=Path, help="default: results/benchmarks/throughput_<time>")
    args = parser.parse_args()
    contenders = ([Contender(*_named(text), peer=False) for text in args.contender or ["fdmo=--no-rrd"]]
                  + [Contender(*_named(text), peer=True) for text in args.peer])
    out = args.out or Path("results/benchmarks") / f"throughput_{time.strftime('%Y%m%d-%H%M%S')}"
    ground_truth = open_dataset(args.folder, DatasetConfig()).ground_truth
    for round_index in range(1, args.runs + 1):
        for contender in contenders:
            run_out = out / contender.name / f"run_{round_index}"
            contender.runs.append(_run(contender, args.folder, run_out, ground_truth))
            print(f"{contender.name} run {round_index}: {contender.runs[-1]}", file=sys.stderr)
    table = markdown_table([_row(contender) for contender in contenders], HEADER)
    print(table)
    out.mkdir(parents=True, exist_ok=True)
    (out / "throughput.md").write_text(table + "\n")
    return 0


def _named(text: str) -> tuple[str, str]:
    name, _, arguments = text.partition("=")
    return name, arguments


def _run(contender: Contender, folder: Path, out: Path, ground_truth) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    trajectory = out / "trajectory.tum"
    if contender.peer:
        command = shlex.split(contender.arguments.format(folder=folder, trajectory=trajectory))
    else:
        command = [sys.executable, "-m", "app", "run", str(folder), "--quiet", "--out", str(out),
                   *shlex.split(contender.arguments)]
    start = time.perf_counter()
    with open(out / "stdout.txt", "w") as stdout:
        process = subprocess.Popen(command, stdout=stdout, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{contender.name} failed ({command}): see {out / 'stdout.txt'}")
    run = {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "rss_mb": usage.ru_maxrss / 1024.0}
    if contender.peer:
        run["ate"] = evaluate(read_trajectory(trajectory), ground_truth, align="sim3")["ate"]["rmse"]
    else:
        metrics = json.loads((out / "metrics.json").read_text())
        run["keyframes"] = metrics["keyframes"]
        run["ate"] = (metrics.get("evaluation") or {}).get("ate", {}).get("rmse")
    return run


def _row(contender: Contender) -> tuple[str, ...]:
    runs = contender.runs
    walls = [run["wall_s"] for run in runs]
    ates = [run["ate"] for run in runs if run["ate"] is not None]
    keyframes = sorted({run["keyframes"] for run in runs if "keyframes" in run})
    return (
        contender.name, str(len(runs)),
        f"{statistics.median(walls):.1f} ({min(walls):.1f}-{max(walls):.1f})",
        f"{statistics.median(run['cpu_s'] for run in runs):.1f}",
        f"{max(run['rss_mb'] for run in runs):.0f}",
        "/".join(map(str, keyframes)) or "-",
        f"{statistics.median(ates):.4f}" if ates else "-",
    )


if __name__ == "__main__":
    sys.exit(main())
