"""Injected faults on a rendered sequence, judged by the result files of real runs (issue 17; the whole matrix, on the
shared folders too, is benchmarks/faults.py): no crash, every frame a trajectory line or a reason in events.jsonl, a
trajectory that parses, no pose for an image that carries no information, the events the fault must cause (and none
it must not); and FDMO keeps one scale through the faults it can see past."""

from __future__ import annotations

import numpy as np
import pytest

from app.fault_runs import CaseReport, account_frames, run_case, run_fault
from vo_core.config import load_config
from vo_core.datasets import open_sequence
from vo_core.synthetic import make_sequence
from vo_core.synthetic.faults import Fault, inject, write_tum_rgbd

WIDTH, HEIGHT, FRAMES, AT = 320, 240, 40, 20
SMOOTH = make_sequence("smooth", FRAMES, seed=0, width=WIDTH, height=HEIGHT)
# Every kind of fault for fdmo; direct where its answer differs (no recovery: a new map instead).
CASES = [("fdmo", Fault("black", AT, 1)), ("fdmo", Fault("black", AT, 10)), ("fdmo", Fault("frozen", AT, 5)),
         ("fdmo", Fault("noise", AT, 5)), ("fdmo", Fault("grey", AT, 5)), ("fdmo", Fault("exposure", AT)),
         ("fdmo", Fault("drop", AT, 10)), ("fdmo", Fault("jump_back", AT, 10)), ("fdmo", Fault("corrupt_file", AT)),
         ("fdmo", Fault("missing_file", AT)), ("direct", Fault("black", AT, 10)), ("direct", Fault("drop", AT, 10))]
# Faults after which FDMO's trajectory is the clean run's (one scale, no new map): ATE against it, metres (the clean
# run's own ATE is 0.0008 m).
SAME_SCALE = {"black", "frozen", "noise", "grey", "drop", "jump_back", "corrupt_file", "missing_file"}
SAME_SCALE_ATE = 0.001


def explain(report: CaseReport) -> str:
    account = report.account
    return (f"{report.method} {report.fault}: {report.outcome}, posed {account and account.posed} of {report.played}, "
            f"reasons {account and dict(account.reasons)}, unexplained {account and account.unexplained}, blind poses "
            f"{account and account.blind_poses}, missing {report.missing_events}, unwanted {report.unwanted_events}, "
            f"events {dict(report.events)}")


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> dict[str, CaseReport]:
    out = tmp_path_factory.mktemp("clean")
    return {method: run_case(SMOOTH, load_config(overrides=[f"method={method}"]), out / method)
            for method in ("fdmo", "direct")}


@pytest.fixture(scope="module")
def on_disk(tmp_path_factory):
    """The same frames as a TUM RGB-D folder, for the file faults."""
    return open_sequence(write_tum_rgbd(SMOOTH, tmp_path_factory.mktemp("disk") / "synthetic"))


@pytest.mark.parametrize("method, fault", CASES, ids=[f"{method}-{fault.name}" for method, fault in CASES])
def test_every_frame_is_posed_or_explained(method, fault, clean, on_disk, tmp_path):
    source = on_disk if fault.kind.endswith("_file") else SMOOTH
    report = run_fault(source, fault, load_config(overrides=[f"method={method}"]), tmp_path, clean[method])
    assert report.passed, explain(report)
    if method == "fdmo" and fault.kind in SAME_SCALE:
        assert report.ate_vs_clean < SAME_SCALE_ATE, explain(report)


@pytest.mark.parametrize("preset, sensor_noise", [("static", False), ("static", True), ("rotation", False)])
def test_no_map_without_a_baseline(preset, sensor_noise, tmp_path):
    """A camera that stands still (its images the same bit for bit, or as a real sensor gives them) or only turns:
    nothing to triangulate, so no initialization, and every frame says so."""
    sequence = make_sequence(preset, FRAMES, seed=0, width=WIDTH, height=HEIGHT)
    if sensor_noise:
        sequence = inject(sequence, Fault("sensor_noise")).sequence
    report = run_case(sequence, load_config(), tmp_path, label=preset, kind=preset)
    assert report.passed and report.account.posed == 0, explain(report)


def test_frames_posed_in_a_start_found_wrong_are_accounted_retracted():
    """A start taken back (initialization_rejected) takes its poses with it: its first frame (named) and the frames it
    posed (listed) are explained by that event, not left unexplained."""
    played = [(index, index / 30.0) for index in range(6)]
    events = [{"frame": 0, "kind": "initialization_started", "details": {}},
              {"frame": 2, "kind": "initialization_succeeded", "details": {"first_frame": 0}},
              {"frame": 4, "kind": "initialization_rejected", "details": {"first_frame": 0, "retracted": [2 / 30, 3 / 30]}},
              {"frame": 4, "kind": "initialization_started", "details": {}}]
    account = account_frames(played, np.array([5 / 30]), events)
    assert account.unexplained == [] and account.posed == 1
    assert account.reasons == {"retracted": 3, "initializing": 2}  # frames 0, 2, 3; frames 1 and 4
