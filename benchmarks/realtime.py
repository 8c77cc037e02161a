"""Live input (``fdmo run FOLDER --realtime``) run several times, each as its own process, and tabulated (issue 18).

    python3 benchmarks/realtime.py ../shared/data/tum_fr3_teddy_first200 --runs 8 [--method fdmo] [--load N] [-- --set k=v]

A live run depends on timing (the frames that arrive while the odometry is busy are dropped), so one run says little:
each row is one whole ``fdmo run FOLDER --realtime --no-rrd --quiet`` process, as a user starts it, with its files
under --out. Per run: frames processed and posed (of the sequence), keyframes, ATE (Sim(3)-aligned RMSE of the posed
frames, vo_core.eval), the frames dropped right after the start frame, divergences reported, whether it was lost
(a reinitialization, or no pose to evaluate), and its silent stretches (poses at another scale than the map's with
nothing reported, benchmarks/real_data.py's measure). The summary line gives the medians and counts that BENCHMARKS.md
quotes. ``--load N`` runs N busy processes (at the run's own priority) beside each run, from before it starts until it
ends: a machine shared with other work (issue 48: one such process on a two-core machine). Arguments after ``--`` go
to ``fdmo run``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.real_data import silent_stretches, trajectories  # noqa: E402
from benchmarks.run_shared import markdown_table  # noqa: E402

HEADER = ("run", "processed", "posed", "keyframes", "ATE m", "dropped after the start", "divergences", "lost",
          "silent")
BUSY_LOOP = "while True: pass"  # the load: one core's worth of CPU-bound work


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--method", default="fdmo")
    parser.add_argument("--far-off", type=float, default=0.05,
                        help="the ATE (m) above which a run counts as far off (default 0.05: teddy offline is 0.0085)")
    parser.add_argument("--load", type=int, default=0, help="busy processes beside each run (default: none)")
    parser.add_argument("--out", type=Path, help="default: results/benchmarks/realtime_<time>")
    args, run_args = parser.parse_known_args()
    run_args = [a for a in run_args if a != "--"]
    out = args.out or Path("results/benchmarks") / f"realtime_{time.strftime('%Y%m%d-%H%M%S')}"
    runs = []
    for index in range(1, args.runs + 1):
        run_out = out / f"run_{index}"
        command = [sys.executable, "-m", "app", "run", str(args.folder), "--method", args.method, "--realtime",
                   "--no-rrd", "--quiet", "--out", str(run_out), *run_args]
        with busy_processes(args.load):
            subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        runs.append(read_run(run_out))
        print(f"run {index}: {runs[-1]}", file=sys.stderr)
    table = markdown_table([row(i, run) for i, run in enumerate(runs, 1)], HEADER)
    print(table)
    print(summary(runs, args.far_off))
    return 0


@contextlib.contextmanager
def busy_processes(count: int):
    """``count`` CPU-bound processes for as long as the block runs."""
    busy = [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(count)]
    try:
        yield
    finally:
        for process in busy:
            process.kill()
            process.wait()


def read_run(folder: Path) -> dict:
    metrics = json.loads((folder / "metrics.json").read_text())
    events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
    kinds = Counter(event["kind"] for event in events)
    ate = (metrics.get("evaluation") or {}).get("ate", {}).get("rmse")
    first_drop = next((e["details"]["count"] for e in events if e["kind"] == "frames_dropped"), 0)
    return {"processed": metrics["processed_frames"], "posed": metrics["posed_frames"],
            "keyframes": metrics["keyframes"], "ate": ate, "first_drop": first_drop,
            "divergences": kinds["divergence_detected"], "lost": ate is None or kinds["reinitialization"] > 0,
            "frames": metrics["frames"],
            "silent": silent_stretches(*judged, events) if (judged := trajectories(folder, metrics)) else 0}


def row(index: int, run: dict) -> tuple[str, ...]:
    ate = "-" if run["ate"] is None else f"{run['ate']:.4f}"
    return (str(index), str(run["processed"]), str(run["posed"]), str(run["keyframes"]), ate,
            str(run["first_drop"]), str(run["divergences"]), "yes" if run["lost"] else "", str(run["silent"] or ""))


def summary(runs: list[dict], far_off_m: float) -> str:
    ates = [run["ate"] for run in runs if run["ate"] is not None]
    drops = [run["first_drop"] for run in runs]
    far = sum(1 for ate in ates if ate > far_off_m)
    processed = statistics.median(run["processed"] / run["frames"] for run in runs)
    return (f"{len(runs)} runs: lost {sum(run['lost'] for run in runs)}, ATE above {far_off_m} m {far}, "
            f"silent stretches {sum(run['silent'] for run in runs)}, median ATE {statistics.median(ates):.4f} m, "
            f"median processed {statistics.median(run['processed'] for run in runs)} ({processed:.0%}), "
            f"dropped after the start {min(drops)}-{max(drops)}"
            if ates else f"{len(runs)} runs: none posed")


if __name__ == "__main__":
    sys.exit(main())
