"""Runs with injected faults (vo_core.synthetic.faults), judged by the result files they leave (issue 17).

A run passes when it did not crash; every frame it played has a line in trajectory.tum or a reason in
events.jsonl (dropped, skipped, repeated, lost, initializing); trajectory.tum parses; no frame whose image carries
no information (black, grey, noise) got a pose; and the events the fault must cause are there. Its ATE is
measured against the ground truth and against the clean run of the same method (the clean run's estimate,
played as the fault plays it: the fault's own cost, whatever the method's accuracy).

    clean = run_case(sequence, config, out / "clean")
    report = run_fault(sequence, Fault("black", at=30, count=10), config, out / "black", clean)

``benchmarks/faults.py`` runs the whole matrix on the shared folders; tests/test_faults.py the synthetic part.
"""

from __future__ import annotations

import json
import tempfile
import traceback
from collections import Counter
from collections.abc import Sequence as SequenceOf
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.pipeline import open_dataset, run_sequence
from app.sinks.files import EVENTS_FILE, TRAJECTORY_FILE
from vo_core.config import Config
from vo_core.errors import InputError
from vo_core.eval import evaluate
from vo_core.events import EventKind
from vo_core.synthetic.faults import FILE_FAULTS, Fault, copy_with_file_fault, inject
from vo_core.trajectory import Trajectory, read_trajectory

MIN_POSES_FOR_ATE = 3
SAME_TIME_S = 1e-6  # trajectory.tum writes nanoseconds

# Events that say why a frame got no pose, in the order a reason is picked when a frame has several.
LOST_EVENTS = (EventKind.TRACKING_FAILED, EventKind.RECOVERY_FAILED, EventKind.DIVERGENCE_DETECTED)
FAILURE_EVENTS = frozenset(kind.value for kind in LOST_EVENTS)
# What each kind of case must cause (every set must meet the events of the run) and must not (a static camera or
# a pure rotation gives no baseline to build a map on). The rest is reported, not required.
EXPECTED_EVENTS: dict[str, tuple[frozenset[str], ...]] = {
    "black": (FAILURE_EVENTS,),
    "grey": (FAILURE_EVENTS,),
    "noise": (FAILURE_EVENTS,),
    "frozen": (frozenset({EventKind.FRAME_REPEATED.value}),),
    "drop": (frozenset({EventKind.FRAMES_DROPPED.value}),),
    "corrupt_file": (frozenset({EventKind.FRAME_SKIPPED.value}),),
    "missing_file": (frozenset({EventKind.FRAME_SKIPPED.value}),),
}
UNWANTED_EVENTS: dict[str, frozenset[str]] = {
    "static": frozenset({EventKind.INITIALIZATION_SUCCEEDED.value}),
    "rotation": frozenset({EventKind.INITIALIZATION_SUCCEEDED.value}),
}


@dataclass
class FrameAccount:
    """What became of every frame played."""

    posed: int = 0
    reasons: Counter = field(default_factory=Counter)  # frames without a pose, by the reason the events give
    unexplained: list[int] = field(default_factory=list)  # frame indices with neither a pose nor a reason
    blind_poses: list[int] = field(default_factory=list)  # posed, unreported, although their image carries nothing


@dataclass
class CaseReport:
    sequence: str
    fault: str
    method: str
    played: int  # frames the sequence offered (dropped ones included)
    outcome: str  # "completed", "refused: <the one-line error>", "crashed: <exception>"
    account: FrameAccount | None = None
    trajectory_parses: bool = False
    estimate: Trajectory | None = None
    ate: float | None = None  # against the ground truth, after Sim(3) alignment
    ate_vs_clean: float | None = None  # against the clean run's estimate, after Sim(3) alignment
    events: Counter = field(default_factory=Counter)
    missing_events: list[str] = field(default_factory=list)  # expected and not seen
    unwanted_events: list[str] = field(default_factory=list)  # seen and not wanted

    @property
    def passed(self) -> bool:
        """No crash, every frame accounted for, a parsing trajectory, no blind pose, the expected events."""
        account = self.account
        return (self.outcome == "completed" and self.trajectory_parses and account is not None
                and not account.unexplained and not account.blind_poses and not self.missing_events
                and not self.unwanted_events)


def run_fault(sequence, fault: Fault, config: Config, out_dir: Path, clean: CaseReport | None = None,
              seed: int = 0) -> CaseReport:
    """``sequence`` with ``fault`` through ``config.method``; file faults need a dataset sequence (its folder is
    copied with the fault)."""
    if fault.kind in FILE_FAULTS:
        return _run_file_fault(sequence, fault, config, out_dir, clean)
    case = inject(sequence, fault, seed)
    reference = None if clean is None or clean.estimate is None else case.sequence.retime(clean.estimate)
    return run_case(case.sequence, config, out_dir, label=fault.name, kind=fault.kind, drops=case.drops,
                    blind=case.sequence.indices[list(case.blind)], reference=reference)


def _run_file_fault(sequence, fault: Fault, config: Config, out_dir: Path, clean: CaseReport | None) -> CaseReport:
    reference = None if clean is None else clean.estimate
    with tempfile.TemporaryDirectory(prefix="fdmo_fault_") as scratch:
        copy = copy_with_file_fault(sequence, Path(scratch) / sequence.root.name, fault.kind, fault.at)
        try:
            faulty = open_dataset(copy, config.dataset)
        except InputError as error:
            return CaseReport(sequence.name, fault.name, config.method, len(sequence), f"refused: {error}")
        return run_case(faulty, config, out_dir, label=fault.name, kind=fault.kind, reference=reference)


def run_case(sequence, config: Config, out_dir: Path, *, label: str = "clean", kind: str | None = None,
             drops: SequenceOf[tuple[int, int]] = (), blind: SequenceOf[int] = (),
             reference: Trajectory | None = None) -> CaseReport:
    """One run through app.pipeline.run_sequence (the real result files), then judged from those files against
    what a case of ``kind`` (a fault kind, "static", "rotation") must and must not cause."""
    report = CaseReport(sequence.name, label, config.method, len(sequence), "completed")
    try:
        run_sequence(sequence, config, out_dir, drops=drops)
    except Exception as error:  # the point of the exercise: any exception is a finding, with its traceback
        report.outcome = f"crashed: {type(error).__name__}: {error}"
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "crash.txt").write_text(traceback.format_exc())
    events = _read_events(Path(out_dir) / EVENTS_FILE)
    report.events = Counter(event["kind"] for event in events)
    report.estimate = _read_estimate(Path(out_dir) / TRAJECTORY_FILE)
    report.trajectory_parses = report.estimate is not None
    played = list(zip(np.asarray(sequence.indices, int).tolist(), np.asarray(sequence.timestamps, float)))
    posed_times = np.zeros(0) if report.estimate is None else report.estimate.timestamps
    report.account = account_frames(played, posed_times, events, set(np.asarray(blind, int).tolist()))
    report.ate = _ate(report.estimate, getattr(sequence, "ground_truth", None))
    report.ate_vs_clean = _ate(report.estimate, reference)
    seen = set(report.events)
    report.missing_events = ["|".join(sorted(kinds)) for kinds in EXPECTED_EVENTS.get(kind, ()) if not kinds & seen]
    report.unwanted_events = sorted(UNWANTED_EVENTS.get(kind, frozenset()) & seen)
    return report


def account_frames(played: list[tuple[int, float]], posed_times: np.ndarray, events: list[dict],
                   blind: set[int] = frozenset()) -> FrameAccount:
    """For each played frame (index, timestamp): posed (a trajectory line at its time), or the reason the events
    give: dropped (inside a frames_dropped range), skipped, repeated, lost (tracking or recovery failed, divergence),
    retracted (posed in a start found wrong: initialization_rejected lists it, or names it as the start's first
    frame), initializing (from initialization_started until the next pose, other than the start's own first frame);
    else unexplained."""
    kinds_at: dict[int, set[str]] = {}
    dropped: set[int] = set()
    retracted_frames: set[int] = set()
    retracted_times: list[float] = []
    for event in events:
        kinds_at.setdefault(event["frame"], set()).add(event["kind"])
        if event["kind"] == EventKind.FRAMES_DROPPED.value:
            dropped.update(range(event["details"]["first_frame"], event["details"]["last_frame"] + 1))
        if event["kind"] == EventKind.INITIALIZATION_REJECTED.value:
            retracted_frames.add(event["details"].get("first_frame"))
            retracted_times += event["details"].get("retracted", [])
    retracted_times = np.sort(np.asarray(retracted_times, float))
    # A start's first frame is posed when the start succeeds, frames later: its pose ends no initialization.
    first_frames = {event["details"].get("first_frame") for event in events
                    if event["kind"] == EventKind.INITIALIZATION_SUCCEEDED.value}
    account = FrameAccount()
    posed_times = np.sort(posed_times)
    initializing = False
    for index, timestamp in played:
        kinds = kinds_at.get(index, set())
        initializing = (initializing or EventKind.INITIALIZATION_STARTED.value in kinds) and not (
            kinds & {EventKind.INITIALIZATION_SUCCEEDED.value, EventKind.DIRECT_RESTARTED.value})
        if _contains(posed_times, timestamp):
            account.posed += 1
            initializing = initializing and index in first_frames
            # --method direct keeps a diverged pose as DSO would, but says so: reported, not silent.
            if index in blind and EventKind.DIVERGENCE_DETECTED.value not in kinds:
                account.blind_poses.append(index)
            continue
        retracted = index in retracted_frames or _contains(retracted_times, timestamp)
        reason = "retracted" if retracted else _reason(index, kinds, dropped, initializing)
        if reason is None:
            account.unexplained.append(index)
        else:
            account.reasons[reason] += 1
    return account


def _reason(index: int, kinds: set[str], dropped: set[int], initializing: bool) -> str | None:
    if index in dropped:
        return "dropped"
    if EventKind.FRAME_SKIPPED.value in kinds:
        return "skipped"
    if EventKind.FRAME_REPEATED.value in kinds:
        return "repeated"
    if kinds & FAILURE_EVENTS:
        return "lost"
    if initializing or kinds & {EventKind.INITIALIZATION_FAILED.value, EventKind.REINITIALIZATION.value}:
        return "initializing"
    return None


def _contains(sorted_times: np.ndarray, timestamp: float) -> bool:
    where = np.searchsorted(sorted_times, timestamp - SAME_TIME_S)
    return where < len(sorted_times) and abs(sorted_times[where] - timestamp) <= SAME_TIME_S


def _read_events(path: Path) -> list[dict]:
    """events.jsonl, every line parsed (a line that does not parse fails loudly: that is a finding)."""
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _read_estimate(path: Path) -> Trajectory | None:
    """trajectory.tum as ``fdmo eval`` reads it; a file of comment lines only is an empty trajectory; None when it
    is missing or does not parse."""
    if not path.is_file():
        return None
    if all(not line.strip() or line.lstrip().startswith("#") for line in path.read_text().splitlines()):
        return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
    try:
        return read_trajectory(path, "tum")
    except InputError:
        return None


def _ate(estimate: Trajectory | None, reference: Trajectory | None) -> float | None:
    if estimate is None or reference is None or len(estimate) < MIN_POSES_FOR_ATE:
        return None
    try:
        return float(evaluate(estimate, reference, align="sim3")["ate"]["rmse"])
    except InputError:  # too few poses matched, or an estimate that never moved
        return None
