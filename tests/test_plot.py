"""``fdmo plot``: a results folder written by the FilesSink drawn as one PNG, with and without ground truth."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from app.cli import main
from app.plot import THRESHOLD_LABEL, draw, read_run, view_axes
from app.sinks.files import FilesSink
from vo_core.config import load_config
from vo_core.events import Event, EventKind, FrameResult
from vo_core.geometry.lie import se3_exp, sim3, so3_exp
from vo_core.trajectory import Trajectory

FRAMES = 40
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def true_pose(i: int) -> np.ndarray:
    return se3_exp(np.array([0.05 * i, 0.002 * i, np.sin(0.2 * i), 0.0, 0.02 * i, 0.0]))


def write_results(out: Path, with_ground_truth: bool = True, with_residuals: bool = True, threshold: float = 1.1,
                  events_at: dict[int, list[EventKind]] | None = None) -> None:
    """What a run leaves: an estimate that is the truth seen through a similarity, plus noise; a divergence at
    frame 20 unless ``events_at`` says which events come at which frames."""
    events_at = {20: [EventKind.DIVERGENCE_DETECTED]} if events_at is None else events_at
    files = FilesSink(out)
    files.begin(load_config())
    S = sim3(0.5, so3_exp(np.array([0.1, -0.4, 0.2])), np.array([1.0, 2.0, -0.5]))
    rng = np.random.default_rng(0)
    for i in range(FRAMES):
        T = S @ true_pose(i)
        T[:3, :3] /= 0.5
        T[:3, 3] += rng.normal(scale=0.002, size=3)
        rmse = (10.0, 6.0 + (5.0 if i == 20 else 0.0)) if with_residuals else (None, None)
        for kind in events_at.get(i, []):
            files.on_event(Event(kind, i, 0.1 * i))
        files.on_frame(None, FrameResult(i, 0.1 * i, T, True, i % 5 == 0, *rmse,
                                         divergence_threshold=threshold if with_residuals else None))
    if with_ground_truth:
        files.write_ground_truth(Trajectory(0.1 * np.arange(FRAMES), [true_pose(i) for i in range(FRAMES)]))
    files.write_metrics({"sequence": "walk", "method": "direct"})
    files.close()


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


@pytest.mark.parametrize("with_ground_truth, with_residuals", [(True, True), (False, True), (True, False)])
def test_plot_draws_a_png_of_the_run(tmp_path, capsys, with_ground_truth, with_residuals):
    write_results(tmp_path, with_ground_truth, with_residuals)
    assert main(["plot", str(tmp_path)]) == 0
    stdout = capsys.readouterr().out
    width, height = png_size(tmp_path / "plot.png")
    assert 800 <= width <= 2000 and 400 <= height <= 1500
    image = cv2.imread(str(tmp_path / "plot.png"), cv2.IMREAD_GRAYSCALE)
    assert image.std() > 10  # something is drawn
    assert stdout.startswith("walk (direct): ") and f"wrote {tmp_path / 'plot.png'}" in stdout
    assert ("ATE rmse" in stdout) == with_ground_truth


def test_the_plotted_ate_is_the_one_eval_gives(tmp_path, capsys):
    write_results(tmp_path)
    assert main(["plot", str(tmp_path), "--out", str(tmp_path / "mine.png")]) == 0
    title = capsys.readouterr().out
    assert main(["eval", str(tmp_path / "trajectory.tum"), str(tmp_path / "groundtruth.tum"), "--json"]) == 0
    evaluation = json.loads(capsys.readouterr().out)
    assert (f"ATE rmse {evaluation['ate']['rmse']:.4f} m over {FRAMES} poses "
            f"(sim3, scale {evaluation['scale']:.3f})") in title
    assert png_size(tmp_path / "mine.png")[0] > 0


def test_unreadable_inputs_are_one_line_errors(tmp_path, capsys):
    write_results(tmp_path / "run", with_ground_truth=False)
    (tmp_path / "gt.txt").write_text("not a trajectory\n")
    assert main(["plot", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.txt")]) == 2
    assert capsys.readouterr().err.startswith("fdmo: error:")
    (tmp_path / "run" / "events.jsonl").write_text('{"frame": 3, "kind"\n')  # cut short
    assert main(["plot", str(tmp_path / "run")]) == 2
    assert "a result file does not parse" in capsys.readouterr().err


def test_views_are_the_widest_plane_and_the_third_axis_or_the_plane_asked_for():
    positions = np.column_stack([np.linspace(0, 10, 5), np.linspace(0, 0.1, 5), np.linspace(0, 3, 5)])
    assert view_axes(positions, None) == ((0, 2), (0, 1))
    assert view_axes(positions, "xy") == ((0, 1), (0, 2))
    assert view_axes(positions, "yz") == ((1, 2), (1, 0))


def ratio_panel(result_dir: Path):
    figure = draw(read_run(result_dir), None, None, "test")
    return next(axes for axes in figure.axes if axes.get_title() == "direct alignment: residual ratio")


def test_the_ratio_panel_draws_the_runs_divergence_threshold(tmp_path):
    """Issue 47: the dashed line sat at 1.0, not at the threshold 1 + epsilon of the run."""
    write_results(tmp_path, threshold=1.25)
    (line,) = [line for line in ratio_panel(tmp_path).get_lines() if line.get_label() == THRESHOLD_LABEL]
    assert np.all(line.get_ydata() == 1.25)


def test_drops_jumps_and_a_divergence_with_its_recovery_on_one_frame_are_all_marked_apart(tmp_path):
    write_results(tmp_path, events_at={10: [EventKind.FRAMES_DROPPED], 20: [EventKind.DIVERGENCE_DETECTED,
                                                                             EventKind.RECOVERY_SUCCEEDED],
                                       30: [EventKind.FRAMES_JUMPED]})
    markers = {line.get_label(): line for line in ratio_panel(tmp_path).get_lines() if line.get_marker() != "None"}
    assert {"frames dropped", "frames jumped", "divergence detected", "recovery succeeded"} <= set(markers)
    divergence, recovery = markers["divergence detected"], markers["recovery succeeded"]
    assert divergence.get_xdata()[0] == recovery.get_xdata()[0]  # the same frame...
    assert divergence.get_ydata()[0] != recovery.get_ydata()[0]  # ...in lanes of their own
