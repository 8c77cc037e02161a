"""``fdmo run | eval | info`` and the pipeline behind ``run``, on tiny dataset folders the tests write.

Most checks run ``main(argv)`` in process with a scripted front end standing in for the odometry (so they
test the app, fast); a few run the real command in a subprocess, with a real method.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import vo_core.system
from app.cli import _incidents, main
from app.pipeline import run_sequence
from app.player import Player
from app.progress import ProgressBar
from app.sinks.files import RESULT_FILES
from ply_reader import read_ply
from vo_core.config import METHODS, load_config
from vo_core.datasets import LAYOUTS, open_sequence
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot
from vo_core.geometry.lie import se3_exp, sim3, so3_exp
from vo_core.synthetic import make_sequence
from vo_core.trajectory import Trajectory, read_trajectory, write_trajectory

REPO = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT, FRAMES = 160, 120, 12
VAMR_INTERVAL_S = 0.1  # the VAMR layout has no timestamps: frame index x 0.1 s
ESTIMATE_SCALE = 2.0  # the scripted front end's poses are the truth at another scale (monocular)


def true_pose(i: int) -> np.ndarray:
    return se3_exp(np.array([0.05 * i, 0.01 * i, 0.02 * i, 0.0, 0.01 * i, 0.0]))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """A VAMR-layout folder: textured images sliding sideways, K.txt, poses.txt (ground truth)."""
    root = tmp_path_factory.mktemp("vamr_tiny")
    (root / "images").mkdir()
    texture = cv2.GaussianBlur(np.random.default_rng(0).uniform(0, 255, (HEIGHT, WIDTH + 3 * FRAMES)), (0, 0), 1.5)
    for i in range(FRAMES):
        cv2.imwrite(str(root / "images" / f"img_{i:05d}.png"), texture[:, 3 * i:3 * i + WIDTH].astype(np.uint8))
    np.savetxt(root / "K.txt", [[100.0, 0, (WIDTH - 1) / 2], [0, 100.0, (HEIGHT - 1) / 2], [0, 0, 1]])
    np.savetxt(root / "poses.txt", [true_pose(i)[:3].reshape(-1) for i in range(FRAMES)])
    return root


@pytest.fixture(scope="module")
def rendered_dataset(tmp_path_factory) -> Path:
    """A VAMR-layout folder of rendered frames (vo_core.synthetic, smooth hand-held motion) and their true poses."""
    sequence = make_sequence("smooth", num_frames=24, seed=0, width=320, height=240)
    root = tmp_path_factory.mktemp("vamr_rendered")
    (root / "images").mkdir()
    for frame in sequence:
        cv2.imwrite(str(root / "images" / f"img_{frame.index:05d}.png"), frame.image)
    np.savetxt(root / "K.txt", sequence.camera.K)
    np.savetxt(root / "poses.txt", sequence.ground_truth.poses[:, :3, :].reshape(len(sequence), 12))
    return root


class ScriptedFrontEnd:
    """Stands in for a method: initializes at frame 2, reports the true pose (scaled), a keyframe every 3."""

    instances: list["ScriptedFrontEnd"] = []

    def __init__(self, interrupt_at: int | None = None, at_frame=None, events_at=None, snapshot=None):
        self.seen: list[int] = []
        self.keyframes: dict[int, np.ndarray] = {}
        self.interrupt_at = interrupt_at
        self.at_frame = at_frame or {}  # frame index -> a function called as that frame is processed
        self.events_at = events_at or {}  # frame index -> kinds of the events it reports
        self.snapshot = snapshot or MapSnapshot()
        ScriptedFrontEnd.instances.append(self)

    def process(self, frame) -> FrameResult:
        assert frame.image.shape == (HEIGHT, WIDTH)
        if frame.index == self.interrupt_at:
            raise KeyboardInterrupt
        if frame.index in self.at_frame:
            self.at_frame[frame.index]()
        result = self._result(frame)
        result.events += [Event(kind, frame.index, frame.timestamp) for kind in self.events_at.get(frame.index, ())]
        return result

    def _result(self, frame) -> FrameResult:
        self.seen.append(frame.index)
        if len(self.seen) < 3:
            return FrameResult(frame.index, frame.timestamp, None, False, timings_ms={"track": 1.0})
        T = true_pose(frame.index)
        T[:3, 3] *= ESTIMATE_SCALE
        keyframe = len(self.seen) % 3 == 0
        if keyframe:
            self.keyframes[frame.index] = T
        events = [Event(EventKind.INITIALIZATION_SUCCEEDED, frame.index, frame.timestamp)] if len(self.seen) == 3 else []
        return FrameResult(frame.index, frame.timestamp, T, True, keyframe, timings_ms={"track": 2.0}, events=events)

    def map_snapshot(self) -> MapSnapshot:
        return MapSnapshot(self.snapshot.direct_points_world, self.snapshot.direct_inverse_depths,
                           self.snapshot.feature_points_world, dict(self.keyframes))

    def final_keyframe_poses(self) -> dict[int, np.ndarray]:
        return dict(self.keyframes)


@pytest.fixture
def scripted(monkeypatch):
    """Every Odometry built during the test gets a ScriptedFrontEnd; returns the list of them (the last one ran
    the sequence: ``fdmo run`` builds one first to check the method) and the options of the next one."""
    ScriptedFrontEnd.instances = []
    options: dict = {}
    monkeypatch.setattr(vo_core.system, "make_front_end", lambda config, camera, start_witness: ScriptedFrontEnd(**options))
    return ScriptedFrontEnd.instances, options


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def events_of(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]


# ------------------------------------------------------------------------------------------------ run


def test_a_stride_plays_every_kth_frame_at_its_own_time_and_says_so(dataset, tmp_path, scripted, capsys):
    """--stride 3: the camera at a third of its rate; the frames keep their numbers and timestamps, and metrics.json
    and the summary say what was played."""
    out = tmp_path / "results"
    code, stdout, _ = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--stride", "3")
    assert code == 0 and "(every 3 frames)" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["stride"] == 3 and metrics["frames"] == len(range(0, FRAMES, 3))
    assert scripted[0][-1].seen == list(range(0, FRAMES, 3))
    posed = read_trajectory(out / "trajectory.tum").timestamps  # the scripted front end poses from its third frame
    np.testing.assert_allclose(posed, np.arange(0, FRAMES, 3)[2:] * VAMR_INTERVAL_S, atol=1e-9)
    code, _, err = run_cli(capsys, "run", dataset, "--out", out, "--stride", "0")
    assert code == 2 and "--stride 0: must be 1 or more" in err


def test_run_writes_the_five_files_and_they_parse_back(dataset, tmp_path, scripted, capsys):
    out = tmp_path / "results"
    code, stdout, _ = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet", "--set", "seed=3")
    assert code == 0 and stdout == ""
    assert all((out / name).is_file() for name in RESULT_FILES)

    trajectory = read_trajectory(out / "trajectory.tum")
    assert len(trajectory) == FRAMES - 2
    np.testing.assert_allclose(trajectory.timestamps, np.arange(2, FRAMES) * VAMR_INTERVAL_S, atol=1e-9)
    assert len(read_trajectory(out / "keyframes.tum")) == len(scripted[0][-1].keyframes)
    assert [e["kind"] for e in events_of(out)] == ["initialization_succeeded"]
    assert set(events_of(out)[0]) == {"frame", "timestamp", "kind", "details"}

    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["frames"], metrics["tracked_frames"], metrics["initialization_frame"]) == (FRAMES, 10, 2)
    assert metrics["status"] == "completed" and metrics["fps"] > 0
    assert metrics["timing_ms"]["track"] == {"mean": pytest.approx(1.0 + 10 / 12), "median": 2.0, "max": 2.0}
    assert set(metrics["timing_ms"]["step"]) == {"mean", "median", "max"}
    # The scripted poses are the truth at twice the scale: Sim(3) alignment makes them exact.
    assert metrics["evaluation"]["ate"]["rmse"] < 1e-6
    config = load_config(out / "config.yaml")
    assert (config.method, config.seed) == ("fdmo", 3)


def test_a_rerun_recording_is_written_by_default_or_where_asked(dataset, tmp_path, scripted, capsys):
    assert run_cli(capsys, "run", dataset, "--out", tmp_path / "a", "--quiet", "--end", "4")[0] == 0
    assert (tmp_path / "a" / "recording.rrd").stat().st_size > 0
    assert run_cli(capsys, "run", dataset, "--out", tmp_path / "b", "--quiet", "--end", "4", "--rrd", tmp_path / "x.rrd")[0] == 0
    assert (tmp_path / "x.rrd").stat().st_size > 0 and not (tmp_path / "b" / "recording.rrd").exists()


def test_a_recording_in_parts_is_named_in_the_summary_with_how_to_open_it(dataset, tmp_path, scripted, capsys,
                                                                          monkeypatch):
    """--rrd-part-frames 5: the 12 frames in three files, which the summary counts and opens together."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    out = tmp_path / "r"
    code, stdout, _ = run_cli(capsys, "run", dataset, "--out", out, "--rrd-part-frames", "5")
    assert code == 0
    assert sorted(path.name for path in out.glob("recording*.rrd")) == [
        "recording.part2.rrd", "recording.part3.rrd", "recording.rrd"]
    assert f"the recording is in 3 files: rerun {out / 'recording*.rrd'} opens them as one" in stdout
    assert f"rerun --serve-web {out / 'recording*.rrd'} shows the recording in a browser" in stdout


def test_dropped_frames_never_reach_the_odometry_and_an_event_says_so(dataset, tmp_path, scripted, capsys):
    out = tmp_path / "results"
    code, _, _ = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet", "--drop", "5:3", "--drop", "10:1")
    assert code == 0
    assert scripted[0][-1].seen == [0, 1, 2, 3, 4, 8, 9, 11]
    drops = [e for e in events_of(out) if e["kind"] == "frames_dropped"]
    assert [(e["frame"], e["details"]["count"], e["details"]["last_frame"]) for e in drops] == [(5, 3, 7), (10, 1, 10)]
    assert json.loads((out / "metrics.json").read_text())["dropped_frames"] == 4


def test_realtime_with_a_slow_tracker_skips_frames_and_says_how_many(dataset, tmp_path, scripted, capsys):
    """Frames every 0.1 s, a tracker taking 0.25 s a frame: about 3 frames in 5 arrive while it is busy."""
    instances, options = scripted
    options["at_frame"] = {i: lambda: time.sleep(2.5 * VAMR_INTERVAL_S) for i in range(FRAMES)}
    out = tmp_path / "results"
    code, stdout, stderr = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--realtime")
    assert code == 0 and "ready after" in stderr  # a synthetic warm-up ran before the camera started
    assert len(instances) == 3  # the method checked, warmed up on a synthetic sequence, then run
    metrics = json.loads((out / "metrics.json").read_text())
    seen = instances[-1].seen
    assert metrics["processed_frames"] == len(seen) and metrics["late_frames"] == FRAMES - len(seen)
    assert 2 <= len(seen) <= FRAMES // 2 and metrics["dropped_frames"] == 0
    assert f"{FRAMES - len(seen)} frames skipped in real time" in stdout
    late = [e for e in events_of(out) if e["kind"] == "frames_dropped"]
    assert {e["details"]["source"] for e in late} == {"realtime"}


def test_a_backward_jump_replays_frames_and_the_trajectory_stays_a_valid_tum_file(dataset, tmp_path, scripted,
                                                                                   capsys):
    out = tmp_path / "results"
    code, stdout, _ = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--jump", "8:4", "--drop", "10:1")
    assert code == 0
    assert scripted[0][-1].seen == [0, 1, 2, 3, 4, 5, 6, 7, 8, 4, 5, 6, 7, 8, 9, 11]
    jumps = [e for e in events_of(out) if e["kind"] == "frames_jumped"]
    assert [(e["frame"], e["details"]["to_frame"], e["details"]["direction"]) for e in jumps] == [(8, 4, "backward")]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["processed_frames"] == 16 and metrics["jumps"] == [{"from_frame": 8, "to_frame": 4}]
    # One line per timestamp, the latest pose: frames 2-11 less the dropped 10 (the front end poses from its 3rd frame).
    assert len(read_trajectory(out / "trajectory.tum")) == metrics["posed_frames"] == 9
    assert "1 frame dropped, 1 jump (8 -> 4)" in stdout
    code, evaluation, _ = run_cli(capsys, "eval", out / "trajectory.tum", out / "groundtruth.tum", "--json")
    assert code == 0 and json.loads(evaluation)["ate"]["rmse"] == pytest.approx(metrics["evaluation"]["ate"]["rmse"],
                                                                             abs=1e-6)


def test_start_and_end_cut_the_sequence_and_keep_frame_numbers(dataset, tmp_path, scripted, capsys):
    code, _, _ = run_cli(capsys, "run", dataset, "--out", tmp_path / "r", "--no-rrd", "--quiet", "--start", "4", "--end", "9")
    assert code == 0
    assert scripted[0][-1].seen == [4, 5, 6, 7, 8]


def test_an_unreadable_image_is_skipped_with_an_event(dataset, tmp_path, scripted, capsys):
    broken = tmp_path / "broken"
    subprocess.run(["cp", "-r", str(dataset), str(broken)], check=True)
    (broken / "images" / "img_00004.png").write_bytes(b"not a png")
    out = tmp_path / "results"
    assert run_cli(capsys, "run", broken, "--out", out, "--no-rrd", "--quiet")[0] == 0
    assert 4 not in scripted[0][-1].seen and len(scripted[0][-1].seen) == FRAMES - 1
    skipped = [e for e in events_of(out) if e["kind"] == "frame_skipped"]
    assert len(skipped) == 1 and "img_00004.png" in skipped[0]["details"]["error"]


def test_an_interrupted_run_leaves_valid_files_and_exits_130(dataset, tmp_path, scripted, capsys):
    scripted[1]["interrupt_at"] = 7
    out = tmp_path / "results"
    code, _, stderr = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet")
    assert code == 130 and "interrupted" in stderr
    assert len(read_trajectory(out / "trajectory.tum")) == 7 - 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["processed_frames"] == 7


def test_a_restart_starts_a_fresh_odometry_and_rewrites_the_files(dataset, tmp_path, scripted):
    sequence = open_sequence(dataset)
    player = Player(sequence)

    class RestartAtFrame5:
        def on_frame(self, frame, result):
            if frame.index == 5 and len(scripted[0]) == 1:
                player.request_restart()

        def on_event(self, event): ...
        def on_map(self, snapshot): ...
        def close(self): ...

    summary = run_sequence(sequence, load_config(), tmp_path / "r", [RestartAtFrame5()], player=player)
    first, second = scripted[0]
    assert first.seen == [0, 1, 2, 3, 4, 5] and second.seen == list(range(FRAMES))
    assert summary.status == "completed" and summary.tracked_frames == 10
    assert len(read_trajectory(tmp_path / "r" / "trajectory.tum")) == FRAMES - 2


def wait_until(condition, timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_with_a_live_view_the_run_stays_up_until_stopped_and_restarts_on_request(dataset, tmp_path, scripted):
    sequence = open_sequence(dataset)
    player = Player(sequence)
    summaries = []
    run = threading.Thread(target=lambda: summaries.append(
        run_sequence(sequence, load_config(), tmp_path / "r", player=player, keep_alive=True)), daemon=True)
    run.start()
    assert wait_until(lambda: player.finished)
    time.sleep(0.1)
    assert run.is_alive()  # the sequence ended, the view stays up
    player.request_restart()
    assert wait_until(lambda: len(scripted[0]) == 2 and len(scripted[0][1].seen) == FRAMES)
    player.stop()
    run.join(timeout=5.0)
    assert not run.is_alive() and summaries[0].status == "completed"
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["processed_frames"] == FRAMES


# ------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "{missing}"], "no such file"),
        (["run", "{dataset}", "--method", "orbslam"], "invalid choice"),
        (["run", "{dataset}", "--set", "seed"], "expected key=value"),
        (["run", "{dataset}", "--set", "klt.nonsense=1"], "unknown config key"),
        (["run", "{dataset}", "--drop", "5"], "FRAME:COUNT"),
        (["run", "{dataset}", "--drop", "40:2"], "not among the frames played (0..11)"),
        (["run", "{dataset}", "--jump", "5"], "FRAME:TARGET"),
        (["run", "{dataset}", "--jump", "5:5"], "FRAME and TARGET must be >= 0 and differ"),
        (["run", "{dataset}", "--jump", "40:2"], "--jump 40:2: frame 40 is not among the frames played (0..11)"),
        (["run", "{dataset}", "--jump", "5:40"], "--jump 5:40: frame 40 is not in the sequence played (0..11)"),
        (["run", "{dataset}", "--viser", "--port", "70000"], "between 1 and 65535"),
        (["run", "{dataset}", "--rrd-part-frames", "-5"], "--rrd-part-frames -5: must be 0 or more"),
        (["run", "{dataset}", "--no-rrd", "--rrd-part-frames", "100"], "cannot be used with --no-rrd"),
        (["run", "{dataset}", "--format", "nonsense"], "invalid choice: 'nonsense'"),
        (["run", "{dataset}", "--set", "direct.tracker.huber_threshold=abc"], "cannot read 'abc' as a number"),
        (["run", "{dataset}", "--set", "seed=2.5"], "cannot read 2.5 as an integer"),
        (["run", "{dataset}", "--set", "direct.window.enabled=maybe"], "cannot read 'maybe' as true or false"),
        (["run", "{dataset}", "--set", "direct.tracker.max_iterations=5"], "cannot read 5 as a list"),
        (["run", "{dataset}", "--set", "seed=[1"], "malformed YAML"),
        (["run", "{dataset}", "--gt", "{missing}"], "trajectory file not found"),
        (["plot", "{empty}"], "not a results folder"),
        (["info", "{empty}"], "unknown dataset layout"),
        (["eval", "{missing}", "{missing}"], "missing"),
        (["frobnicate"], "invalid choice"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, message, dataset, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("nothing to see")
    paths = {"dataset": dataset, "missing": tmp_path / "missing", "empty": tmp_path / "empty"}
    out = ["--out", tmp_path / "out"] if argv[0] == "run" else []
    code, stdout, stderr = run_cli(capsys, *[a.format(**paths) for a in argv], *out)
    assert code == 2
    assert len(stderr.strip().splitlines()) == 1 and stderr.startswith("fdmo: error:") and message in stderr
    assert not (tmp_path / "out").exists()  # nothing half-written


def test_help_lists_the_layouts_the_methods_and_the_port_default(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines anywhere
    assert exit_info.value.code == 0
    assert "{" + ",".join(LAYOUTS) + "}" in text and "{" + ",".join(METHODS) + "}" in text
    assert "port of the viser page (default: 8080)" in text and "(default: 127.0.0.1" in text


# ------------------------------------------------------------------------------------------ summary


def test_the_summary_names_what_befell_the_run(dataset, tmp_path, scripted, capsys):
    broken = tmp_path / "broken"
    subprocess.run(["cp", "-r", str(dataset), str(broken)], check=True)
    (broken / "images" / "img_00004.png").write_bytes(b"not a png")
    scripted[1]["events_at"] = {
        6: [EventKind.DIVERGENCE_DETECTED, EventKind.RECOVERY_TRIED, EventKind.RECOVERY_SUCCEEDED],
        7: [EventKind.DIVERGENCE_DETECTED, EventKind.RECOVERY_FAILED, EventKind.TRACKING_FAILED,
            EventKind.REINITIALIZATION],
        8: [EventKind.KEYFRAME_ADDED],
    }
    code, stdout, _ = run_cli(capsys, "run", broken, "--out", tmp_path / "r", "--no-rrd", "--drop", "9:2")
    assert code == 0
    assert "(fdmo, completed): tracked 7/9 frames, initialized at frame 2, 1 keyframe," in stdout
    assert ("1 unreadable frame skipped, 2 frames dropped, 1 tracking failure, 2 divergences, "
            "2 recoveries (1 succeeded, 1 failed), 1 reinitialization") in stdout
    assert "ATE rmse" in stdout and f"results in {tmp_path / 'r'}" in stdout


def test_the_summary_counts_the_loops_closed_and_the_maps_merged():
    metrics = {"events": {"loop_closed": 2, "maps_merged": 1, "loop_candidate": 40}, "skipped_frames": 0,
               "dropped_frames": 0, "late_frames": 0, "jumps": []}
    assert _incidents(metrics) == ["2 loops closed", "1 map merged into the final one"]


@pytest.mark.parametrize("display", [None, ":0"])
def test_without_a_display_the_summary_says_how_to_open_the_recording_in_a_browser(dataset, tmp_path, scripted,
                                                                                   capsys, monkeypatch, display):
    """`rerun FILE` fails without a display (winit's EventLoopError); `rerun --serve-web FILE` does not."""
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if display is None:
        monkeypatch.delenv("DISPLAY", raising=False)
    else:
        monkeypatch.setenv("DISPLAY", display)
    code, stdout, _ = run_cli(capsys, "run", dataset, "--out", tmp_path / "r")
    hint = f"no display here: rerun --serve-web {tmp_path / 'r' / 'recording.rrd'} shows the recording in a browser"
    assert code == 0 and (hint in stdout) == (display is None)


def test_the_summary_says_never_initialized_and_names_nothing_that_did_not_happen(dataset, tmp_path, scripted,
                                                                                  capsys):
    code, stdout, _ = run_cli(capsys, "run", dataset, "--out", tmp_path / "r", "--no-rrd", "--end", "2")
    assert code == 0 and "never initialized" in stdout and "frame None" not in stdout
    assert not any(word in stdout for word in ("skipped", "dropped", "failure", "divergence", "recover"))


def test_keyframes_are_counted_by_their_events(dataset, tmp_path, scripted, capsys):
    """An initializer announces its first keyframe frames after that frame was tracked: metrics.json counts the
    keyframe_added events, as keyframes.tum lists them, not the frames flagged as keyframes when tracked."""
    scripted[1]["events_at"] = {i: [EventKind.KEYFRAME_ADDED] for i in (3, 5, 9)}
    assert run_cli(capsys, "run", dataset, "--out", tmp_path / "r", "--no-rrd", "--quiet")[0] == 0
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["keyframes"] == 3


# ------------------------------------------------------------------------------------------ signals


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_ends_the_run_after_the_current_frame_with_a_summary_and_128_plus_its_number(
        dataset, tmp_path, scripted, capsys, signum):
    scripted[1]["at_frame"] = {6: lambda: os.kill(os.getpid(), signum)}
    out = tmp_path / "results"
    code, stdout, stderr = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd")
    assert code == {signal.SIGINT: 130, signal.SIGTERM: 143}[signum]
    assert stderr.strip().endswith(f"fdmo: interrupted; results in {out}")
    assert scripted[0][-1].seen == list(range(7))  # frame 6, during which the signal came, was finished
    assert "(fdmo, interrupted): tracked 5/7 frames" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["processed_frames"] == 7
    assert len(read_trajectory(out / "trajectory.tum")) == 5
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handlers are given back


def test_a_second_signal_stops_at_once_and_still_exits_130(dataset, tmp_path, scripted, capsys):
    def twice():
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)

    scripted[1]["at_frame"] = {6: twice}
    out = tmp_path / "results"
    code, _, stderr = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet")
    assert code == 130 and stderr.strip() == f"fdmo: interrupted; results in {out}"
    assert json.loads((out / "metrics.json").read_text())["status"] == "interrupted"


def test_an_interrupt_inside_a_compiled_kernel_exits_130(dataset, tmp_path, scripted, capsys):
    """numba reports a KeyboardInterrupt raised inside a kernel as a SystemError caused by it."""
    def kernel_interrupted():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as error:
            raise SystemError("CPUDispatcher(<function kernel>) returned a result with an exception set") from error

    scripted[1]["at_frame"] = {6: kernel_interrupted}
    out = tmp_path / "results"
    code, _, stderr = run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet")
    assert code == 130 and stderr.strip() == f"fdmo: interrupted; results in {out}"
    assert json.loads((out / "metrics.json").read_text())["status"] == "interrupted"


# ------------------------------------------------------------------------------------------ outputs


def test_ground_truth_of_the_run_is_written_and_evaluates_as_metrics_json(dataset, tmp_path, scripted, capsys):
    out = tmp_path / "r"
    assert run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet", "--start", "1", "--end", "9")[0] == 0
    ground_truth = read_trajectory(out / "groundtruth.tum")
    np.testing.assert_allclose(ground_truth.timestamps, np.arange(1, 9) * VAMR_INTERVAL_S, atol=1e-9)
    np.testing.assert_allclose(ground_truth.poses, [true_pose(i) for i in range(1, 9)], atol=1e-6)
    _, evaluation, _ = run_cli(capsys, "eval", out / "trajectory.tum", out / "groundtruth.tum", "--json")
    metrics = json.loads((out / "metrics.json").read_text())
    evaluation = json.loads(evaluation)  # the files keep 9 decimals: ATE to 1e-8
    assert evaluation["matched_poses"] == metrics["evaluation"]["matched_poses"] == 6
    assert evaluation["ate"] == pytest.approx(metrics["evaluation"]["ate"], abs=1e-8)


def test_maps_are_written_as_ply_the_empty_ones_not(dataset, tmp_path, scripted, capsys):
    rng = np.random.default_rng(1)
    direct = rng.normal(size=(50, 3))
    direct[7] = np.nan  # a point no viewer can draw
    scripted[1]["snapshot"] = MapSnapshot(direct, rng.uniform(0.2, 2.0, 50), np.zeros((0, 3)))
    out = tmp_path / "r"
    assert run_cli(capsys, "run", dataset, "--out", out, "--no-rrd", "--quiet")[0] == 0
    points, colors = read_ply(out / "map_direct.ply")
    np.testing.assert_allclose(points, np.delete(direct, 7, axis=0), rtol=1e-6)
    assert colors.shape == (49, 3) and len(np.unique(colors, axis=0)) > 1  # colored by inverse depth
    assert not (out / "map_features.ply").exists()


def test_gt_option_gives_ground_truth_to_ones_own_data(dataset, tmp_path, scripted, capsys):
    own = tmp_path / "own"
    subprocess.run(["cp", "-r", str(dataset / "images"), str(own)], check=True)
    (own / "camera.yaml").write_text(f"model: pinhole\nintrinsics: [100, 100, {(WIDTH - 1) / 2}, {(HEIGHT - 1) / 2}]\n"
                                     f"resolution: [{WIDTH}, {HEIGHT}]\n")
    truth = Trajectory(np.arange(FRAMES) * VAMR_INTERVAL_S, np.array([true_pose(i) for i in range(FRAMES)]))
    write_trajectory(tmp_path / "gt.tum", truth, "tum")
    write_trajectory(tmp_path / "gt.kitti", truth, "kitti")  # no timestamps: a line per image
    for name in ("gt.tum", "gt.kitti"):
        out = tmp_path / name.replace(".", "_")
        assert run_cli(capsys, "run", own, "--out", out, "--no-rrd", "--quiet", "--gt", tmp_path / name)[0] == 0
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["evaluation"]["matched_poses"] == FRAMES - 2 and metrics["evaluation"]["ate"]["rmse"] < 1e-6
        assert (out / "groundtruth.tum").is_file()
    far = Trajectory(truth.timestamps + 1000.0, truth.poses)
    write_trajectory(tmp_path / "far.tum", far, "tum")
    code, _, stderr = run_cli(capsys, "run", own, "--out", tmp_path / "far", "--gt", tmp_path / "far.tum")
    assert code == 2 and "does not overlap the images" in stderr


def test_viser_listens_on_this_machine_only_unless_asked(dataset, tmp_path, scripted, capsys, monkeypatch):
    """... and plays at the sequence's frame rate, from when a browser opens the page."""
    import app.sinks.viser_view

    hosts, playback = [], []

    class FakeView:
        url = "http://fake"

        def __init__(self, camera, player, ground_truth=None, host="?", port=0, wait_for_browser=False, title=""):
            hosts.append(host)
            playback.append((player.speed, wait_for_browser))
            player.stop()  # the page would be the way to quit

        def on_frame(self, frame, result): ...
        def on_event(self, event): ...
        def on_map(self, snapshot): ...
        def close(self): ...

    monkeypatch.setattr(app.sinks.viser_view, "ViserView", FakeView)
    for extra in ([], ["--host", "0.0.0.0"]):
        code, _, _ = run_cli(capsys, "run", dataset, "--out", tmp_path / "r", "--no-rrd", "--quiet", "--viser", *extra)
        assert code == 0
    assert hosts == ["127.0.0.1", "0.0.0.0"]
    assert playback == [(1.0, True)] * 2


# ------------------------------------------------------------------------------------------ eval, info


@pytest.fixture
def trajectory_files(tmp_path) -> tuple[Path, Path]:
    """Ground truth, and an estimate that is the truth seen through a similarity (scale 0.5)."""
    timestamps = np.arange(40) * 0.05
    truth = np.array([se3_exp(np.array([np.sin(t), 0.3 * t, np.cos(2 * t), 0.1 * t, 0.2 * np.sin(t), 0.0]))
                      for t in timestamps])
    S = sim3(0.5, so3_exp(np.array([0.1, -0.4, 0.2])), np.array([1.0, 2.0, -0.5]))
    estimate = truth.copy()
    estimate[:, :3, :3] = S[:3, :3] / 0.5 @ truth[:, :3, :3]
    estimate[:, :3, 3] = truth[:, :3, 3] @ S[:3, :3].T + S[:3, 3]
    write_trajectory(tmp_path / "gt.tum", Trajectory(timestamps, truth), "tum")
    write_trajectory(tmp_path / "est.tum", Trajectory(timestamps, estimate), "tum")
    return tmp_path / "est.tum", tmp_path / "gt.tum"


def test_eval_prints_the_ate_after_alignment(trajectory_files, capsys):
    estimate, truth = trajectory_files
    code, stdout, _ = run_cli(capsys, "eval", estimate, truth)
    assert code == 0 and "ate" in stdout.lower() and "rmse" in stdout
    _, aligned, _ = run_cli(capsys, "eval", estimate, truth, "--json")
    _, unaligned, _ = run_cli(capsys, "eval", estimate, truth, "--align", "none", "--json")
    assert json.loads(aligned)["ate"]["rmse"] < 1e-6
    assert json.loads(unaligned)["ate"]["rmse"] > 0.5


def test_info_prints_what_the_loader_found(dataset, capsys):
    code, stdout, _ = run_cli(capsys, "info", dataset)
    assert code == 0 and "layout: vamr" in stdout
    description = json.loads(run_cli(capsys, "info", dataset, "--json")[1])
    assert (description["layout"], description["frames"], description["resolution"]) == ("vamr", FRAMES, [WIDTH, HEIGHT])
    assert description["ground_truth"]["poses"] == FRAMES
    synthetic = json.loads(run_cli(capsys, "info", "synthetic:forward:12:160x120", "--json")[1])
    assert (synthetic["layout"], synthetic["frames"], synthetic["resolution"]) == ("synthetic", 12, [160, 120])


def test_progress_bar_reports_rate_tracked_fraction_and_last_event():
    stream = io.StringIO()
    progress = ProgressBar(4, stream=stream)
    progress.on_frame(None, FrameResult(0, 0.0, None, False))
    progress.on_event(Event(EventKind.FRAMES_DROPPED, 1, 0.1, {"count": 2}))
    progress.on_event(Event(EventKind.KEYFRAME_ADDED, 3, 0.3))
    progress.on_frame(None, FrameResult(3, 0.3, np.eye(4), True))
    progress.close()
    last = stream.getvalue().splitlines()[-1]
    assert "4/4 frames" in last and "fps" in last and "tracked  50%" in last and "keyframe_added@3" in last


# ------------------------------------------------------------------------------------------ subprocess


def test_python_dash_m_app_runs_a_real_method_end_to_end(rendered_dataset, tmp_path):
    out = tmp_path / "results"
    completed = subprocess.run(
        [sys.executable, "-m", "app", "run", str(rendered_dataset), "--method", "direct", "--out", str(out),
         "--no-rrd", "--quiet"],
        cwd=REPO, capture_output=True, text=True, timeout=300,
    )
    assert completed.returncode == 0, completed.stderr
    assert all((out / name).is_file() for name in RESULT_FILES)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "direct" and metrics["processed_frames"] == 24 and metrics["tracked_frames"] >= 8
    # Poses written camera-to-world at the dataset's timestamps: they line up with the truth after Sim(3).
    truth = open_sequence(rendered_dataset).ground_truth.positions
    path_length = np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    assert metrics["evaluation"]["matched_poses"] == len(read_trajectory(out / "trajectory.tum"))
    assert metrics["evaluation"]["ate"]["rmse"] < 0.05 * path_length


def test_a_threaded_fdmo_run_in_its_own_process_ends_with_its_recording_and_files_complete(rendered_dataset, tmp_path):
    """``fdmo run`` ends its process without the interpreter's teardown (app.cli._end_process): the recording is
    flushed, the feature half's process joined and every file written before that."""
    rr = pytest.importorskip("rerun")
    out = tmp_path / "results"
    completed = subprocess.run(
        [sys.executable, "-m", "app", "run", str(rendered_dataset), "--mapping", "threaded", "--out", str(out)],
        cwd=REPO, capture_output=True, text=True, timeout=300,
        env={name: value for name, value in os.environ.items() if name != "PYTHONUNBUFFERED"},  # as a user's shell
    )
    assert completed.returncode == 0, completed.stderr
    assert completed.stdout.strip().splitlines()[-1].strip() == f"results in {out}"  # the summary, flushed
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "fdmo" and metrics["processed_frames"] == 24
    assert len(read_trajectory(out / "trajectory.tum")) == metrics["posed_frames"] > 0
    events = [json.loads(line)["kind"] for line in (out / "events.jsonl").read_text().splitlines()]
    assert events.count("feature_keyframe_added") == metrics["keyframes"]
    recording = rr.chunk.RrdReader(out / "recording.rrd")
    assert recording.blueprints()  # sent last, at the sink's close
    assert {chunk.entity_path for chunk in recording.stream().to_chunks()} >= {"/events", "/world/camera"}


def test_the_fdmo_scripts_module_imports_nothing_a_spawned_process_would_import_again():
    """A process multiprocessing spawns (the feature half's) runs the ``fdmo`` script again, which imports the module
    of its entry point: that module must not import the app (app.cli and, through it, the whole odometry)."""
    entry = next(point for point in importlib.metadata.entry_points(group="console_scripts") if point.name == "fdmo")
    module = entry.value.partition(":")[0]
    imported = subprocess.run([sys.executable, "-c", f"import sys, {module}; print(sorted(m for m in sys.modules "
                                                     "if m.split('.')[0] in ('app', 'vo_core', 'numpy')))"],
                              cwd=REPO, capture_output=True, text=True, timeout=60)
    assert imported.returncode == 0, imported.stderr
    assert imported.stdout.strip() == repr(["app", module])


@pytest.mark.parametrize("argv", [
    ["run", "folder", "--mapping", "threaded"],
    ["run", "--mapping=threaded", "folder"],
    ["run", "folder", "--realtime"],
    ["run", "folder", "--viser", "--no-rrd"],
    ["run", "folder"],
    ["run", "folder", "--realtime", "--mapping", "sync"],
    ["run", "folder", "--mapping", "threaded", "--method", "direct"],
    ["run", "folder", "--method", "direct", "--mapping", "threaded", "--method", "fdmo"],
    ["run", "folder", "--mapping", "threaded", "--method", "klt"],
])
def test_the_command_line_read_by_hand_tells_which_runs_map_features_in_a_process(argv):
    """app/process_start.py reads the command line before anything is imported, to start the feature half's
    process ahead; it must come to what the run's configuration says (vo_core.system)."""
    from app.cli import build_parser, run_config
    from app.process_start import maps_features_in_a_process

    configured = vo_core.system.maps_features_in_a_process(run_config(build_parser().parse_args(argv)))
    assert maps_features_in_a_process(argv) is configured
    assert not maps_features_in_a_process(["bench", *argv[1:]]) and not maps_features_in_a_process([])


def test_the_fdmo_command_starts_the_feature_process_before_it_imports_the_app():
    script = ("import sys; from vo_core.features import feature_process; "
              "feature_process.start_ahead = lambda: print('ahead; app.cli imported:', 'app.cli' in sys.modules); "
              "sys.argv = ['fdmo', 'run', '--mapping', 'threaded', '--help']; from app.__main__ import main; main()")
    completed = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 0, completed.stderr
    assert completed.stdout.splitlines()[0] == "ahead; app.cli imported: False"


def test_a_live_runs_warm_up_leaves_the_run_its_feature_process_started_ahead():
    """The warm-up's throwaway odometry maps on this thread; the feature process started for the run gets ready
    beside it and is still waiting afterwards, not closed with the throwaway."""
    from app.pipeline import warm_up
    from vo_core.features import feature_process

    warm_up(load_config(None, ["mapping.threaded=true"]), make_sequence("smooth", 2, width=160, height=120).camera,
            num_frames=6)
    (process, connection), = feature_process._ahead
    feature_process._ahead.clear()
    assert process.is_alive()
    connection.close()  # it ends
    process.join(10)
    assert process.exitcode == 0


def test_bad_input_in_a_subprocess_is_one_line_and_no_traceback(tmp_path):
    completed = subprocess.run([sys.executable, "-m", "app", "run", str(tmp_path / "nowhere")],
                               cwd=REPO, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert completed.stderr.strip().splitlines() == [f"fdmo: error: {tmp_path / 'nowhere'}: no such file or folder"]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_the_compiled_kernels_finishes_the_files_and_exits_128_plus_its_number(tmp_path, signum):
    """The real direct method on the bundled sequence, signalled once it tracks (most of its time is then spent in
    numba kernels, where a KeyboardInterrupt used to surface as a SystemError and exit 1)."""
    out = tmp_path / "results"
    process = subprocess.Popen([sys.executable, "-m", "app", "run", "--out", str(out), "--no-rrd", "--quiet"],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    poses = out / "trajectory.tum"
    assert wait_until(lambda: poses.is_file() and len(poses.read_text().splitlines()) > 6, timeout_s=240)
    process.send_signal(signum)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143}[signum], stderr
    assert stderr.strip().splitlines() == [f"fdmo: interrupted; results in {out}"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["processed_frames"] < 80
    assert len((out / "frames.csv").read_text().splitlines()) == 1 + metrics["processed_frames"]
    assert len(read_trajectory(poses)) == metrics["posed_frames"]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_a_viser_run_exits_as_interrupted_as_metrics_json_says(tmp_path, signum):
    """Issue 47: Ctrl-C on a --viser run exited 0 ("fdmo: stopped") while metrics.json said interrupted. A client
    that sends the page's first camera message stands in for the browser that starts playback."""
    out, port = tmp_path / "results", free_port()
    process = subprocess.Popen([sys.executable, "-m", "app", "run", "--viser", "--port", str(port), "--out", str(out),
                                "--no-rrd", "--quiet"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
    try:
        assert "live view at" in process.stderr.readline()
        with viser_client(port):
            frames = out / "frames.csv"
            assert wait_until(lambda: frames.is_file() and len(frames.read_text().splitlines()) > 3, timeout_s=120)
            process.send_signal(signum)
            _, stderr = process.communicate(timeout=120)
    finally:
        process.kill()
    assert process.returncode == {signal.SIGINT: 130, signal.SIGTERM: 143}[signum], stderr
    assert stderr.strip().splitlines()[-1] == f"fdmo: interrupted; results in {out}"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["processed_frames"] < metrics["frames"]


def free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@contextlib.contextmanager
def viser_client(port: int):
    """A websocket client of the viser page that reports a camera (viser counts a client as connected from its
    first camera message) and reads whatever the page sends, as a browser would."""
    import msgspec
    import viser
    from viser._messages import ViewerCameraMessage
    from websockets.sync.client import connect

    camera = ViewerCameraMessage(wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -1.0), fov=1.0, near=0.01, far=100.0,
                                 image_height=480, image_width=640, look_at=(0.0, 0.0, 0.0),
                                 up_direction=(0.0, -1.0, 0.0))
    with connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"]) as client:
        client.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        threading.Thread(target=_read_until_closed, args=(client,), daemon=True).start()
        yield client


def _read_until_closed(client) -> None:
    with contextlib.suppress(Exception):  # closed: the run ended
        while True:
            client.recv()


def test_a_calibration_for_another_resolution_exits_2_naming_both_sizes(dataset, tmp_path):
    (tmp_path / "folder").mkdir()
    for image in sorted((dataset / "images").iterdir())[:4]:
        (tmp_path / "folder" / image.name).write_bytes(image.read_bytes())
    (tmp_path / "folder" / "camera.yaml").write_text(
        "model: pinhole\nintrinsics: [500, 500, 319.5, 239.5]\nresolution: [640, 480]\n")
    completed = subprocess.run([sys.executable, "-m", "app", "run", str(tmp_path / "folder"), "--out",
                                str(tmp_path / "out")], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert completed.returncode == 2
    assert completed.stderr.strip().splitlines() == [
        f"fdmo: error: {tmp_path / 'folder' / 'img_00000.png'}: the images are {WIDTH}x{HEIGHT}, "
        "but the camera calibration is for 640x480"]
    assert not (tmp_path / "out").exists()


def test_output_read_by_a_reader_that_goes_away_ends_quietly(dataset):
    """``fdmo info X | head``: the pipe closes before fdmo writes."""
    process = subprocess.Popen([sys.executable, "-m", "app", "info", str(dataset)], cwd=REPO,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()  # the only reader: fdmo's first write meets a broken pipe
    stderr = process.stderr.read().decode()
    assert process.wait(timeout=60) == 141 and stderr == ""


# ------------------------------------------------------------------------------------------------ vocabulary


def test_vocabulary_train_writes_a_file_the_feature_map_can_use(rendered_dataset, tmp_path, capsys):
    from vo_core.features.config import VocabularyConfig
    from vo_core.features.vocabulary import load_vocabulary

    out = tmp_path / "voc.npz"
    code, stdout, _ = run_cli(capsys, "vocabulary", "train", rendered_dataset / "images", "--out", out,
                              "--branching", "4", "--depth", "2")
    assert code == 0 and "16 words" in stdout
    vocabulary = load_vocabulary(VocabularyConfig(path=str(out), direct_index_levels_up=1))
    assert (vocabulary.branching, vocabulary.depth) == (4, 2)


def test_vocabulary_train_refuses_what_is_not_an_image(tmp_path, capsys):
    (tmp_path / "notes.png").write_text("not an image")
    code, _, stderr = run_cli(capsys, "vocabulary", "train", tmp_path / "notes.png", "--out", tmp_path / "v.npz")
    assert code == 2 and "notes.png" in stderr and len(stderr.strip().splitlines()) == 1
