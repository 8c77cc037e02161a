"""Live input (``fdmo run FOLDER --realtime``) run several times, each as its own process, and tabulated (issue 18).

    python3 benchmarks/realtime.py ../shared/data/tum_fr3_teddy_first200 --runs 8 [--method fdmo] [-- --set k=v]

A live run depends on timing (the frames that arrive while the odometry is busy are dropped), so one run says little:
each row is one whole ``fdmo run FOLDER --realtime --no-rrd --quiet`` process, as a user starts it, with its files
under --out. Per run: frames processed and posed (of the sequence), keyframes, ATE (Sim(3)-aligned RMSE of the posed
frames, vo_core.eval), the frames dropped right after the start frame, divergences reported, and whether it was lost
(a reinitialization, or no pose to evaluate). The summary line gives the medians and counts that BENCHMARKS.md quotes.
Arguments after ``--`` go to ``fdmo run``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.run_shared import markdown_table  # noqa: E402

HEADER = ("run", "processed", "posed", "keyframes", "ATE m", "dropped after the start", "divergences", "lost")
FAR_OFF_M = 0.05  # the ATE above which a run counts as far off in the summary (teddy offline: 0.0085 m)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--method", default="fdmo")
    parser.add_argument("--out", type=Path, help="default: results/benchmarks/realtime_<time>")
    args, run_args = parser.parse_known_args()
    run_args = [a for a in run_args if a != "--"]
    out = args.out or Path("results/benchmarks") / f"realtime_{time.strftime('%Y%m%d-%H%M%S')}"
    runs = []
    for index in range(1, args.runs + 1):
        run_out = out / f"run_{index}"
        command = [sys.executable, "-m", "app", "run", str(args.folder), "--method", args.method, "--realtime",
                   "--no-rrd", "--quiet", "--out", str(run_out), *run_args]
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        runs.append(read_run(run_out))
        print(f"run {index}: {runs[-1]}", file=sys.stderr)
    table = markdown_table([row(i, run) for i, run in enumerate(runs, 1)], HEADER)
    print(table)
    print(summary(runs))
    return 0


def read_run(folder: Path) -> dict:
    metrics = json.loads((folder / "metrics.json").read_text())
    events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
    kinds = Counter(event["kind"] for event in events)
    ate = (metrics.get("evaluation") or {}).get("ate", {}).get("rmse")
    first_drop = next((e["details"]["count"] for e in events if e["kind"] == "frames_dropped"), 0)
    return {"processed": metrics["processed_frames"], "posed": metrics["posed_frames"],
            "keyframes": metrics["keyframes"], "ate": ate, "first_drop": first_drop,
            "divergences": kinds["divergence_detected"], "lost": ate is None or kinds["reinitialization"] > 0}


def row(index: int, run: dict) -> tuple[str, ...]:
    ate = "-" if run["ate"] is None else f"{run['ate']:.4f}"
    return (str(index), str(run["processed"]), str(run["posed"]), str(run["keyframes"]), ate,
            str(run["first_drop"]), str(run["divergences"]), "yes" if run["lost"] else "")


def summary(runs: list[dict]) -> str:
    ates = [run["ate"] for run in runs if run["ate"] is not None]
    drops = [run["first_drop"] for run in runs]
    far = sum(1 for ate in ates if ate > FAR_OFF_M)
    return (f"{len(runs)} runs: lost {sum(run['lost'] for run in runs)}, ATE above {FAR_OFF_M} m {far}, "
            f"median ATE {statistics.median(ates):.4f} m, median processed "
            f"{statistics.median(run['processed'] for run in runs)}, dropped after the start {min(drops)}-{max(drops)}"
            if ates else f"{len(runs)} runs: none posed")


if __name__ == "__main__":
    sys.exit(main())
