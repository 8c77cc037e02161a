"""``fdmo experiment two-loop``: the two-loop experiment of FDMO section 5.3.1 (the paper's Table 3 and Fig. 5).

    fdmo experiment two-loop SOURCE [--methods fdmo,direct,klt] [--segment 0.2]

Each method, with a fresh odometry, is fed the sequence twice back to back: frames 0..n-1, then 0..n-1 again, so
the jump from the last frame back to the first is part of the test (one more ordinary step on a sequence that
ends where it starts, as TUM monoVO's and the synthetic "loop" do; a large jump on the others). The frames of the
second pass are numbered on after the first pass's and timed t + duration + one frame interval (duration = last
timestamp - first), so that times increase and no frame number or time repeats; their ground truth is shifted
with them.

At the end of each loop, the drifts of the TUM monoVO benchmark (Engel et al. 2016; ``vo_core.eval.loop_drifts``):
the Sim(3) alignments S_s and S_e of the estimate to the ground truth of the first loop's start segment and of this
loop's end segment; the alignment error e_align = sqrt(1/n sum_i ||S_s p_i - S_e p_i||^2) over the n posed frames
up to the end of the loop; the rotation drift (deg), scale drift and translation drift of S_e S_s^-1. TUM monoVO's
ground truth (groundtruthSync.txt covers only the start and the end) gives the segments itself; where the ground
truth covers the whole sequence they are the first and last ``--segment`` share of each loop's matched frames, and
the ATE (Sim(3) over all posed frames up to the end of the loop) is reported too.

Writes loops.csv (a row per method and loop), trajectory_<method>.tum, groundtruth.tum (the ground truth at the
frames of both passes), two_loop.png (Fig. 5: each estimate aligned by S_s over the ground truth, loop 1 solid,
loop 2 dashed) and table.md.
"""

from __future__ import annotations

import argparse
import tempfile

import numpy as np

from app.experiments.common import (
    EVENT_COLUMNS,
    count_events,
    figure,
    finish,
    frame_interval,
    markdown_table,
    relabelled,
    set_up,
    truth_at_frames,
    write_csv,
)
from app.pipeline import track
from app.sinks.files import FilesSink
from vo_core.config import load_config
from vo_core.errors import InputError
from vo_core.eval import Drift, EvalConfig, evaluate, ground_truth_gap_end, loop_drifts
from vo_core.events import FrameResult
from vo_core.trajectory import Trajectory, write_trajectory

NAME = "two-loop"
HELP = "FDMO sec. 5.3.1: the sequence played twice, TUM monoVO drifts at the end of each loop"
LOOPS = 2
DEFAULT_SEGMENT = 0.2  # of each loop's frames: teddy's first 200 frames give 40-frame (1.3 s, ~0.4 m) segments
LOOPS_FILE = "loops.csv"
PLOT_FILE = "two_loop.png"
MIN_POSES_FOR_ATE = 3  # a Sim(3) alignment needs three positions


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--segment", type=float, default=DEFAULT_SEGMENT,
                        help="share of a loop's frames in its start and in its end segment, where the ground truth "
                             "covers the whole sequence (default: %(default)s)")


def run(args: argparse.Namespace) -> None:
    if not 0.0 < args.segment <= 0.5:
        raise InputError(f"--segment {args.segment}: must be in (0, 0.5]")
    setup = set_up(NAME, args, {"loops": LOOPS, "segment": args.segment})
    sequence = setup.sequence
    shift = loop_shift(sequence)
    truth = looped_truth(sequence, shift)
    spans = loop_spans(sequence, shift)
    config = EvalConfig(drift_segment_fraction=args.segment)
    whole = ground_truth_gap_end(truth.within(*spans[0]).timestamps, config) is None
    rows, estimates = [], {}
    for method, method_config in setup.configs.items():
        setup.say(f"{method}: {LOOPS} x {len(sequence)} frames")
        tracked = track(method_config, sequence.camera, looped_frames(sequence, shift))
        results = tracked.results
        estimate = estimated_trajectory(results, tracked.keyframe_poses)
        write_trajectory(setup.out_dir / f"trajectory_{method}.tum", estimate, "tum")
        drifts = loop_drifts(estimate, truth, spans, config)
        rows += [loop_row(method, loop, results, estimate, truth, span, drift, whole)
                 for loop, (span, drift) in enumerate(zip(spans, drifts), start=1)]
        estimates[method] = (estimate, drifts)
    write_csv(setup.out_dir / LOOPS_FILE, rows)
    write_trajectory(setup.out_dir / "groundtruth.tum", truth, "tum")
    plot(estimates, truth, spans, sequence.name).savefig(setup.out_dir / PLOT_FILE, dpi=110)
    finish(setup, table(rows))


def loop_shift(sequence) -> float:
    """How much later each pass is timed than the one before: the sequence's duration plus one frame interval."""
    return float(sequence.timestamps[-1] - sequence.timestamps[0]) + frame_interval(sequence)


def loop_spans(sequence, shift: float) -> list[tuple[float, float]]:
    """The (first, last) times of each pass's frames."""
    first, last = float(sequence.timestamps[0]), float(sequence.timestamps[-1])
    return [(first + loop * shift, last + loop * shift) for loop in range(LOOPS)]


def looped_frames(sequence, shift: float):
    """The sequence ``LOOPS`` times, pass k's frames numbered on by k x (last frame number + 1) and timed on by
    k x ``shift``."""
    numbers = int(np.max(sequence.indices)) + 1
    for loop in range(LOOPS):
        for frame in sequence:
            yield relabelled(frame, frame.index + loop * numbers, frame.timestamp + loop * shift)


def looped_truth(sequence, shift: float) -> Trajectory:
    """The ground truth at the frames of every pass, timed as ``looped_frames`` times them."""
    truth = truth_at_frames(sequence)
    positions = np.array(sorted(truth), dtype=int)
    times = sequence.timestamps[positions]
    poses = np.array([truth[position] for position in positions])
    return Trajectory(np.concatenate([times + loop * shift for loop in range(LOOPS)]), np.tile(poses, (LOOPS, 1, 1)))


def estimated_trajectory(results: list[FrameResult],
                         keyframe_poses: dict[int, np.ndarray] | None = None) -> Trajectory:
    """The poses tracking gave, as ``fdmo run`` writes trajectory.tum: the same results through the same FilesSink
    (a start's first frame posed once it succeeds, a refused start's poses taken back, loops and merges applied, each
    frame hung on its keyframe's final pose where ``keyframe_poses`` has it), in a folder of its own that goes."""
    with tempfile.TemporaryDirectory() as folder:
        files = FilesSink(folder)
        files.begin(load_config())
        for result in results:
            for event in result.events:
                files.on_event(event)
            files.on_frame(None, result)
        files.write_final_poses(keyframe_poses or {})
        estimate = files.estimate()
        files.close()
    return estimate


def loop_row(method: str, loop: int, results: list[FrameResult], estimate: Trajectory, truth: Trajectory,
             span: tuple[float, float], drift: Drift | None, whole_truth: bool) -> dict:
    first, last = span
    in_loop = [result for result in results if first <= result.timestamp <= last]
    drifts = drift.as_dict() if drift is not None else {}
    return {
        "method": method,
        "loop": loop,
        "frames": len(in_loop),
        "posed_frames": sum(result.T_world_cam is not None for result in in_loop),
        "alignment_error_m": drifts.get("alignment_error"),
        "rotation_drift_deg": drifts.get("rotation_drift_deg"),
        "scale_drift": drifts.get("scale_drift"),
        "translation_drift_m": drifts.get("translation_drift"),
        "ate_m": _ate(estimate.within(-np.inf, last), truth.within(-np.inf, last)) if whole_truth else None,
        **count_events(in_loop),
    }


def _ate(estimate: Trajectory, truth: Trajectory) -> float | None:
    """ATE rmse after one Sim(3) alignment; None where there is none (too few poses, no motion, no match)."""
    if len(estimate) < MIN_POSES_FOR_ATE:
        return None
    try:
        return evaluate(estimate, truth)["ate"]["rmse"]
    except InputError:
        return None


# ----------------------------------------------------------------------------------------- table and plot


def table(rows: list[dict]) -> str:
    header = ("method", "loop", "posed frames", "e_align m", "rotation drift deg", "scale drift", "ATE m", "events")
    lines = [(row["method"], row["loop"], f"{row['posed_frames']} of {row['frames']}",
              _number(row["alignment_error_m"], 4), _number(row["rotation_drift_deg"], 2),
              _number(row["scale_drift"], 3), _number(row["ate_m"], 4), _events(row)) for row in rows]
    return markdown_table(header, lines)


def _number(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _events(row: dict) -> str:
    return ", ".join(f"{column.replace('_', ' ')} {row[column]}" for column in EVENT_COLUMNS if row[column]) or "-"


def plot(estimates: dict[str, tuple[Trajectory, list[Drift | None]]], truth: Trajectory,
         spans: list[tuple[float, float]], title: str):
    """FDMO Fig. 5: per method, the estimate aligned by S_s (the first loop's start segment) over the ground
    truth, top view (the plane of the ground truth's two widest axes), loop 1 solid, loop 2 dashed."""
    from app.plot import view_axes

    (u, v), _ = view_axes(truth.positions, None)
    canvas = figure(5 * len(estimates), 5)
    for panel, (method, (estimate, drifts)) in zip(canvas.subplots(1, len(estimates), squeeze=False)[0],
                                                    estimates.items()):
        panel.plot(truth.positions[:, u], truth.positions[:, v], ".", color="0.6", ms=2, label="ground truth")
        start = next((drift.start for drift in drifts if drift is not None), None)
        if start is None:
            panel.set_title(f"{method}: no start segment to align on")
            continue
        for loop, ((first, last), style) in enumerate(zip(spans, ("-", "--")), start=1):
            positions = start.apply(estimate.within(first, last)).positions
            panel.plot(positions[:, u], positions[:, v], style, color=f"C{loop - 1}", lw=1.2, label=f"loop {loop}")
        panel.set(title=method, xlabel="xyz"[u] + " [m]", ylabel="xyz"[v] + " [m]", aspect="equal")
        panel.legend(fontsize="small")
    canvas.suptitle(f"{title}: two loops, aligned on the first loop's start segment", fontsize="medium")
    return canvas
