"""Injected faults on the shared folders and on synthetic sequences, for fdmo and direct (issue 17; BENCHMARKS.md,
"Faults").

    python3 benchmarks/faults.py                                  # everything: ~1 h on one core
    python3 benchmarks/faults.py --sequences synthetic --methods fdmo

Each case runs through app.pipeline.run_sequence, as ``fdmo run --no-rrd`` would, and is judged from its result
files by app.fault_runs: no crash, every frame played has a trajectory line or a reason in events.jsonl, the
trajectory parses, no pose for an image without information, the events the fault must cause (and none it must
not). ATE is against the ground truth; "vs clean" is against the clean run of the same method, played as the
fault plays it. Result folders stay under --out, with report.json; the Markdown table is printed and written to
<out>/faults.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.fault_runs import CaseReport, run_case, run_fault  # noqa: E402
from app.pipeline import open_dataset  # noqa: E402
from vo_core.config import load_config  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.synthetic import make_sequence  # noqa: E402
from vo_core.synthetic.faults import Fault, inject, write_tum_rgbd  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"  # ../shared/data beside the repository
FOLDERS = ("tum_fr3_teddy_first200", "kitti00_first100", "vamr_parking_first200")
SYNTHETIC = "synthetic"
SYNTHETIC_FRAMES, SYNTHETIC_SIZE = 120, (320, 240)
METHODS = ("fdmo", "direct")
FRAMES_AFTER = 10  # a fault ends at least this many frames before the end: room to come back
# (kind, count) of every fault of the matrix.
FAULTS = (("black", 1), ("black", 10), ("black", 60), ("frozen", 10), ("noise", 10), ("grey", 10), ("exposure", 1),
          ("drop", 5), ("drop", 20), ("drop", 60), ("jump_back", 10), ("jump_back", 30), ("corrupt_file", 1),
          ("missing_file", 1))
HEADER = ("sequence", "fault", "method", "frames", "posed", "no pose: why", "unexplained", "blind poses",
          "trajectory parses", "ATE m", "vs clean m", "events", "pass")
# Short names of the events the table counts.
EVENT_COLUMNS = (("tracking_failed", "fail"), ("divergence_detected", "div"), ("tracking_checked", "chk"),
                 ("tracking_unverified", "unverified"), ("recovery_succeeded", "rec"), ("recovery_failed", "rec-fail"),
                 ("direct_resumed", "resume"), ("direct_restarted", "restart"),
                 ("feature_tracking", "feat"), ("reinitialization", "reinit"),
                 ("reinitialization_abandoned", "reinit-abandoned"), ("frame_repeated", "rep"),
                 ("frame_skipped", "skip"), ("frames_dropped", "drop"))


def fault_at(kind: str, count: int, length: int) -> Fault:
    """The fault in the middle of the sequence, ending FRAMES_AFTER frames before its end at the latest (a jump back
    needs ``count`` frames before it)."""
    affected = 1 if kind in ("exposure", "jump_back") else count
    return Fault(kind, max(count if kind == "jump_back" else 0, min(length // 2, length - affected - FRAMES_AFTER)),
                 count)


def run_sequence_cases(name: str, sequence, files_sequence, method: str, out: Path) -> list[CaseReport]:
    """The clean run and every fault of FAULTS on one sequence (``files_sequence``: the same frames on disk, for
    the file faults), then the synthetic presets when the sequence is synthetic."""
    config = load_config(overrides=[f"method={method}"])
    clean = run_case(sequence, config, out / "clean")
    reports = [clean]
    for kind, count in FAULTS:
        fault = fault_at(kind, count, len(sequence))
        source = files_sequence if kind.endswith("_file") else sequence
        print(f"  {name} {method} {fault.name} at {fault.at}", file=sys.stderr, flush=True)
        reports.append(run_fault(source, fault, config, out / fault.name.replace(" ", "_"), clean))
    if name == SYNTHETIC:
        reports += run_presets(config, out)
    for report in reports:
        report.sequence = name
    return reports


def run_presets(config, out: Path) -> list[CaseReport]:
    """A static camera (its images bit-identical, and as a sensor gives them: with noise) and a pure rotation."""
    static = make_synthetic("static")
    noisy = inject(static, Fault("sensor_noise")).sequence
    return [run_case(static, config, out / "static", label="static camera", kind="static"),
            run_case(noisy, config, out / "static_noisy", label="static camera, sensor noise", kind="static"),
            run_case(make_synthetic("rotation"), config, out / "rotation", label="pure rotation", kind="rotation")]


def make_synthetic(preset: str):
    return make_sequence(preset, SYNTHETIC_FRAMES, seed=0, width=SYNTHETIC_SIZE[0], height=SYNTHETIC_SIZE[1])


def table_row(report: CaseReport) -> tuple[str, ...]:
    account = report.account
    if account is None:
        return (report.sequence, report.fault, report.method, str(report.played), "-", report.outcome, "-", "-",
                "-", "-", "-", "-", "no")
    reasons = ", ".join(f"{why} {count}" for why, count in sorted(account.reasons.items())) or "-"
    events = ", ".join(f"{short} {report.events[kind]}" for kind, short in EVENT_COLUMNS if report.events[kind])
    problems = [f"no {kinds}" for kinds in report.missing_events] + [f"unwanted {kind}" for kind in
                                                                       report.unwanted_events]
    if report.outcome != "completed":
        problems.append(report.outcome)
    return (report.sequence, report.fault, report.method, str(report.played), str(account.posed), reasons,
            _frames(account.unexplained), _frames(account.blind_poses), "yes" if report.trajectory_parses else "NO",
            _metres(report.ate), _metres(report.ate_vs_clean), events or "-",
            "yes" if report.passed else "NO: " + "; ".join(problems or ["see the columns"]))


def _frames(indices: list[int]) -> str:
    if not indices:
        return "0"
    return f"{len(indices)} ({indices[0]}..{indices[-1]})"


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def markdown_table(rows: list[tuple[str, ...]]) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows])


def open_cases(name: str, data: Path, scratch: Path):
    """(sequence, the same frames as a dataset folder) of a shared folder or of the synthetic sequence."""
    if name != SYNTHETIC:
        sequence = open_dataset(data / name, load_config().dataset)
        return sequence, sequence
    sequence = make_synthetic("smooth")
    return sequence, open_sequence(write_tum_rgbd(sequence, scratch / SYNTHETIC))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=SHARED_DATA, help="folder holding the shared sequences")
    parser.add_argument("--sequences", nargs="+", default=(*FOLDERS, SYNTHETIC),
                        help=f"folder names under --data, or '{SYNTHETIC}'")
    parser.add_argument("--methods", nargs="+", default=METHODS, choices=METHODS)
    parser.add_argument("--out", type=Path, help="default: results/benchmarks/faults_<time>")
    args = parser.parse_args()
    out = args.out or Path("results/benchmarks") / f"faults_{time.strftime('%Y%m%d-%H%M%S')}"
    reports = []
    with tempfile.TemporaryDirectory(prefix="fdmo_faults_") as scratch:
        for name in args.sequences:
            if name != SYNTHETIC and not (args.data / name).is_dir():
                print(f"skipping {args.data / name}: not found", file=sys.stderr)
                continue
            sequence, files_sequence = open_cases(name, args.data, Path(scratch))
            for method in args.methods:
                reports += run_sequence_cases(name, sequence, files_sequence, method, out / name / method)
                save(reports, out)
    table = markdown_table([table_row(report) for report in reports])
    print(table)
    (out / "faults.md").write_text(table + "\n")
    print(f"written to {out / 'faults.md'}", file=sys.stderr)
    return 0


def save(reports: list[CaseReport], out: Path) -> None:
    """report.json: what the table shows, per case (the result folders have the rest)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "report.json").write_text(json.dumps([as_json(report) for report in reports], indent=1) + "\n")


def as_json(report: CaseReport) -> dict:
    account = report.account
    return {"sequence": report.sequence, "fault": report.fault, "method": report.method, "played": report.played,
            "outcome": report.outcome, "posed": account and account.posed,
            "reasons": account and dict(account.reasons), "unexplained": account and account.unexplained,
            "blind_poses": account and account.blind_poses, "trajectory_parses": report.trajectory_parses,
            "ate": report.ate, "ate_vs_clean": report.ate_vs_clean, "events": dict(report.events),
            "missing_events": report.missing_events, "unwanted_events": report.unwanted_events,
            "passed": report.passed}


if __name__ == "__main__":
    sys.exit(main())
