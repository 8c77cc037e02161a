"""``fdmo plot``: a run drawn from its results folder, as one PNG.

The top and side views of the estimate against ground truth after alignment (Umeyama, Sim(3) by default, fitted on
the poses matched by timestamp, as ``fdmo eval`` does), the estimate colored by its position error; that error over
time; and the ratio RMSE_after / RMSE_before of the direct alignment (FDMO's divergence test: above 1 the alignment
made the residual worse) against the divergence test's threshold 1 + epsilon, where frames.csv has them. Tracking
failures, divergences, recoveries, reinitializations, drops and jumps are marked on the time axes, each kind in a
lane of its own. Without ground truth the views show the estimate alone.

The top view is the plane of the two axes along which the ground truth extends most (the ground, for most
datasets) unless ``plane`` names one (KITTI's camera world is y-down: its ground plane is xz); the side view shows
the first of them against the third axis.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.sinks.files import EVENTS_FILE, FRAMES_FILE, GROUND_TRUTH_FILE, METRICS_FILE, TRAJECTORY_FILE
from vo_core.errors import InputError
from vo_core.eval import DEFAULT_MAX_DT_S, associate, ate_errors, error_statistics, fit_alignment
from vo_core.events import EventKind
from vo_core.trajectory import Trajectory, read_trajectory

AXES = "xyz"
PLANES = ("xy", "xz", "yz")
DEFAULT_PLOT_FILE = "plot.png"
DPI = 110
# Events marked on the time axes: matplotlib's color and marker. Each kind has a lane of its own (a height in the
# panel), so that the events of one frame (a divergence and its recovery) stay apart.
MARKED_EVENTS = {
    EventKind.TRACKING_FAILED.value: ("C3", "x"),
    EventKind.DIVERGENCE_DETECTED.value: ("C1", "v"),
    EventKind.RECOVERY_SUCCEEDED.value: ("C2", "^"),
    EventKind.RECOVERY_FAILED.value: ("C4", "X"),
    EventKind.REINITIALIZATION.value: ("C5", "s"),
    EventKind.FRAMES_DROPPED.value: ("C7", ">"),  # the player's: --drop, the page's button
    EventKind.FRAMES_JUMPED.value: ("C9", "D"),  # --jump, the page's jump back
}
TOP_LANE, LANE_STEP = 0.96, 0.06  # the lanes' heights, as fractions of the panel's height
THRESHOLD_LABEL = "divergence threshold 1 + epsilon"


@dataclass
class Run:
    """What a results folder holds for the plot."""

    name: str
    estimate: Trajectory
    ground_truth: Trajectory | None
    frames: np.ndarray | None  # frames.csv as a structured array (empty fields are NaN)
    events: list[dict]


@dataclass
class Errors:
    """The estimate aligned to the ground truth, and the position error of each pose matched by timestamp."""

    aligned: Trajectory
    matched: Trajectory
    errors: np.ndarray
    scale: float


def read_run(result_dir: Path, ground_truth_file: Path | None = None) -> Run:
    """A results folder of ``fdmo run``; ``ground_truth_file`` replaces its groundtruth.tum."""
    if not (result_dir / TRAJECTORY_FILE).is_file():
        raise InputError(f"{result_dir}: not a results folder of fdmo run (no {TRAJECTORY_FILE})")
    ground_truth_file = ground_truth_file or result_dir / GROUND_TRUTH_FILE
    frames_file, events_file, metrics_file = (result_dir / name for name in (FRAMES_FILE, EVENTS_FILE, METRICS_FILE))
    try:
        metrics = json.loads(metrics_file.read_text()) if metrics_file.is_file() else {}
        frames = np.genfromtxt(frames_file, delimiter=",", names=True, ndmin=1) if frames_file.is_file() else None
        events = [json.loads(line) for line in events_file.read_text().splitlines()] if events_file.is_file() else []
    except ValueError as error:  # a file edited or cut short by hand (JSONDecodeError is a ValueError)
        raise InputError(f"{result_dir}: a result file does not parse ({error})") from None
    return Run(
        name=f"{metrics.get('sequence')} ({metrics.get('method')})" if metrics else result_dir.resolve().name,
        estimate=read_trajectory(result_dir / TRAJECTORY_FILE),
        ground_truth=read_trajectory(ground_truth_file) if ground_truth_file.is_file() else None,
        frames=frames,
        events=events,
    )


def plot_run(result_dir: Path, out: Path, ground_truth_file: Path | None = None, align: str = "sim3",
             plane: str | None = None) -> str:
    """Draw the run in ``result_dir`` into the PNG ``out``; returns the figure's title."""
    run = read_run(result_dir, ground_truth_file)
    errors = None if run.ground_truth is None else position_errors(run.estimate, run.ground_truth, align)
    if errors is None:
        title = f"{run.name}: no ground truth"
    else:
        title = (f"{run.name}: ATE rmse {error_statistics(errors.errors)['rmse']:.4f} m over {len(errors.errors)} "
                 f"poses ({align}, scale {errors.scale:.3f})")
    draw(run, errors, plane, title).savefig(out, dpi=DPI)
    return title


def position_errors(estimate: Trajectory, ground_truth: Trajectory, align: str) -> Errors:
    matched_estimate, matched_truth = associate(estimate, ground_truth, DEFAULT_MAX_DT_S)
    alignment = fit_alignment(matched_estimate, matched_truth, align)
    matched = alignment.apply(matched_estimate)
    return Errors(alignment.apply(estimate), matched, ate_errors(matched, matched_truth), alignment.scale)


def draw(run: Run, errors: Errors | None, plane: str | None, title: str):
    # matplotlib's Figure without pyplot: no global state, no display; savefig renders PNG with Agg.
    from matplotlib.figure import Figure

    estimate = run.estimate if errors is None else errors.aligned
    start = estimate.timestamps[0]
    ratio = rmse_ratio(run.frames)
    below = [name for name, shown in (("error", errors is not None), ("ratio", ratio is not None)) if shown]
    figure = Figure(figsize=(12, 10.5 if below else 5.5), layout="constrained")
    panels = figure.subplot_mosaic([["top", "side"], *([below * (2 // len(below))] if below else [])])
    draw_views(figure, panels["top"], panels["side"], estimate, run.ground_truth, errors, plane)
    if errors is not None:
        panels["error"].plot(errors.matched.timestamps - start, errors.errors, "C0-", lw=1)
        panels["error"].set(ylabel="position error [m]", title="error along the path")
    if ratio is not None:
        times, values = ratio
        panels["ratio"].plot(times - start, values, "C0.", ms=3)
        draw_threshold(panels["ratio"], run.frames, start)
        panels["ratio"].set(ylabel="RMSE after / before", title="direct alignment: residual ratio")
    for name in below:
        panels[name].set_xlabel("time since the first pose [s]")
        mark_events(panels[name], run.events, start)
    figure.suptitle(title, fontsize="medium")
    return figure


def draw_views(figure, top_panel, side_panel, estimate: Trajectory, ground_truth: Trajectory | None,
               errors: Errors | None, plane: str | None) -> None:
    """The top and the side view; the ground truth drawn over the estimate's time span only."""
    if ground_truth is not None:
        ground_truth = ground_truth.within(estimate.timestamps[0] - DEFAULT_MAX_DT_S,
                                           estimate.timestamps[-1] + DEFAULT_MAX_DT_S)
    framed = ground_truth if ground_truth is not None and len(ground_truth) else estimate
    top, side = view_axes(framed.positions, plane)
    colored = draw_view(top_panel, "top", top, estimate, ground_truth, errors)
    draw_view(side_panel, "side", side, estimate, ground_truth, errors)
    if colored is not None:
        figure.colorbar(colored, ax=[top_panel, side_panel], label="position error [m]", shrink=0.8)


def view_axes(positions: np.ndarray, plane: str | None) -> tuple[tuple[int, int], tuple[int, int]]:
    """The (horizontal, vertical) axis indices of the top view and of the side view."""
    if plane is None:
        order = list(np.argsort(np.ptp(positions, axis=0))[::-1])  # widest first
    else:
        order = [AXES.index(axis) for axis in plane]
        order.append(3 - sum(order))  # the remaining axis
    return tuple(sorted(order[:2])), (order[0], order[2])


def draw_view(panel, name: str, axes_pair: tuple[int, int], estimate: Trajectory, ground_truth: Trajectory | None,
              errors: Errors | None):
    """The ``name`` ("top", "side") view of the trajectories; returns the error-colored points (None without
    ground truth)."""
    u, v = axes_pair
    if ground_truth is not None:
        panel.plot(ground_truth.positions[:, u], ground_truth.positions[:, v], "k-", lw=1, label="ground truth")
    panel.plot(estimate.positions[:, u], estimate.positions[:, v], "C0-", lw=0.8, label="estimate")
    panel.plot(*estimate.positions[0, [u, v]], "ko", ms=4, label="start")
    colored = None
    if errors is not None:
        matched = errors.matched.positions
        colored = panel.scatter(matched[:, u], matched[:, v], c=errors.errors, s=8, cmap="viridis", zorder=3)
    # Equal scales on both axes; the limits grow to fill the panel rather than the panel shrinking to a strip.
    panel.set(xlabel=f"{AXES[u]} [m]", ylabel=f"{AXES[v]} [m]", aspect="equal", adjustable="datalim",
              title=f"{name} view ({AXES[u]}{AXES[v]})")
    if name == "top":
        panel.legend(loc="best", fontsize="small")
    return colored


def rmse_ratio(frames: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """(timestamps, RMSE_after / RMSE_before) of the frames that have both; None if none has."""
    if frames is None:
        return None
    before, after = frames["rmse_before"], frames["rmse_after"]
    valid = np.isfinite(before) & np.isfinite(after) & (before > 0)
    return (frames["timestamp"][valid], after[valid] / before[valid]) if valid.any() else None


def draw_threshold(panel, frames: np.ndarray, start: float) -> None:
    """The divergence test's threshold (frames.csv's divergence_threshold, 1 + epsilon), as a dashed line over the
    frames that have one; none in results written before frames.csv had the column."""
    if "divergence_threshold" not in (frames.dtype.names or ()):
        return
    known = np.isfinite(frames["divergence_threshold"])
    if known.any():
        panel.plot(frames["timestamp"][known] - start, frames["divergence_threshold"][known], "k--", lw=0.8,
                   drawstyle="steps-post", label=THRESHOLD_LABEL)


def mark_events(panel, events: list[dict], start: float) -> None:
    """A thin vertical line at each marked event and a marker in its kind's lane; a legend entry per kind that
    occurred."""
    times: dict[str, list[float]] = {}
    for event in events:
        if event["kind"] in MARKED_EVENTS:
            times.setdefault(event["kind"], []).append(event["timestamp"] - start)
    for lane, (kind, (color, marker)) in enumerate(MARKED_EVENTS.items()):
        if kind not in times:
            continue
        for at in times[kind]:
            panel.axvline(at, color=color, lw=0.6, alpha=0.4)
        # x in data, y in the panel's fraction: the lanes stay put whatever the data's range.
        panel.plot(times[kind], [TOP_LANE - lane * LANE_STEP] * len(times[kind]), ls="none", marker=marker,
                   color=color, ms=6, transform=panel.get_xaxis_transform(), label=kind.replace("_", " "))
    if panel.get_legend_handles_labels()[1]:  # the events', and the threshold's
        panel.legend(loc="lower left", fontsize="small")
