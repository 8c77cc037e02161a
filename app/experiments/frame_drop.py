"""``fdmo experiment frame-drop``: the frame-drop experiment of FDMO section 5.3.2 (the paper's Fig. 6).

    fdmo experiment frame-drop SOURCE [--methods fdmo,direct,klt] [--at FRAME ...] [--direction forward|backward|both]
                               [--step 5] [--warmup 40] [--after 10] [--max-error 50] [--rotation-tolerance 2]

Frames are positions in the sequence (0-based: a dataset folder's own frame numbers). One trial, for a method, a
jump frame ``at``, a direction and a jump of N frames, with a fresh odometry:

1. it plays frames ``start..at``, start = max(0, at - warmup). The direct methods initialize 4-6 frames after
   their first frame (the feature initializer) and fill their window of 5-7 keyframes within about 20 frames
   (teddy: a keyframe every 2.7 frames), so the default 40 frames leave them settled; the trials record the
   keyframes made before the jump.
2. the jump: forward, the next frame is at + N + 1 (frames at+1..at+N are never seen, as ``fdmo run --drop
   at+1:N``); backward, it is at - N, and the frames from there are played again. ``after`` frames are played
   from the jump on. The frames after the jump are renumbered and retimed to follow frame ``at`` at the
   sequence's frame interval: the odometry sees one large motion between two consecutive frames and cannot tell
   from the numbers how far the camera went (FDMO's and DSO's motion models never look; the KLT baseline's would).
3. measured (``vo_core.eval.frame_drop_error``): the motion between frame ``at`` and the first frame after the jump
   that got a pose, each pose as the odometry reported it when it tracked that frame, against the ground truth:
   the distance between the camera centres, the estimate's scaled by the Sim(3) (Umeyama) alignment of the posed
   frames start..at to the ground truth, and the geodesic angle between the orientations; % error =
   100 |measured - true| / true. The ground-truth columns are the true motion of that pair.
4. the outcome, the first that applies:
   - ``not_ready``: frame ``at`` got no pose, or the frames before it give no Sim(3) (fewer than 3 posed frames
     with ground truth, or no motion);
   - ``reinitialized``: a reinitialization after the jump (the map is started anew, at a new scale);
   - ``unrecovered``: a tracking failure or a divergence after the jump that no successful recovery follows;
   - ``lost``: no frame after the jump got a pose, or the last one did not;
   - ``error``: a translation error above ``max_error`` %, or a rotation error above ``max_error`` % of the true
     angle and above ``rotation_tolerance`` degrees (the % of a few tenths of a degree means nothing: on the
     sideways parking sequence the true rotation is 0);
   - otherwise ``survived``.

The sweep grows N by ``step`` from ``step`` until a trial does not survive, or until the frames run out
(forward: past the end of the sequence; backward: before the run's first frame; either way frames without
ground truth). Writes trials.csv (a row per trial), frame_drop.png (Fig. 6: % error against the true motion in
metres and degrees, forward and backward) and table.md (each sweep's limit).
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from app.experiments.common import (
    Setup,
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
from vo_core.errors import InputError
from vo_core.eval import fit_alignment, frame_drop_error
from vo_core.events import EventKind, FrameResult
from vo_core.trajectory import Trajectory

NAME = "frame-drop"
HELP = "FDMO sec. 5.3.2: jump forward or back by growing numbers of frames until each method fails"
DIRECTIONS = ("forward", "backward")
TRIALS_FILE = "trials.csv"
PLOT_FILE = "frame_drop.png"
FAILURES = (EventKind.TRACKING_FAILED, EventKind.DIVERGENCE_DETECTED)
MIN_ALIGNED_FRAMES = 3  # a Sim(3) needs three positions that span a plane


@dataclass(frozen=True)
class Protocol:
    step: int = 5  # FDMO sec. 5.3.2: "increased by five frames each time"
    warmup: int = 40  # frames played before the jump frame
    after: int = 10  # frames played from the jump on
    max_error_pct: float = 50.0  # FDMO sec. 5.5: past its limits DSO's pose errors were "of over 50%"
    rotation_tolerance_deg: float = 2.0


@dataclass(frozen=True)
class Plan:
    """The frames of one trial, by position: up to the jump frame, then from the jump on."""

    before: list[int]
    after: list[int]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    defaults = Protocol()
    parser.add_argument("--at", type=int, action="append", metavar="FRAME",
                        help="jump frame, repeatable (default: the middle of the sequence)")
    parser.add_argument("--direction", choices=(*DIRECTIONS, "both"), default="both",
                        help="forward: skip N frames; backward: go on from frame at-N (default: %(default)s)")
    parser.add_argument("--step", type=int, default=defaults.step, help="N grows by this (default: %(default)s)")
    parser.add_argument("--warmup", type=int, default=defaults.warmup,
                        help="frames played before the jump frame (default: %(default)s)")
    parser.add_argument("--after", type=int, default=defaults.after,
                        help="frames played from the jump on (default: %(default)s)")
    parser.add_argument("--max-error", type=float, default=defaults.max_error_pct,
                        help="%% error beyond which a trial fails (default: %(default)s)")
    parser.add_argument("--rotation-tolerance", type=float, default=defaults.rotation_tolerance_deg,
                        help="rotation error in degrees that never fails a trial (default: %(default)s)")


def run(args: argparse.Namespace) -> None:
    protocol = Protocol(args.step, args.warmup, args.after, args.max_error, args.rotation_tolerance)
    if protocol.step < 1 or protocol.warmup < MIN_ALIGNED_FRAMES or protocol.after < 1:
        raise InputError(f"frame-drop: --step and --after must be >= 1 and --warmup >= {MIN_ALIGNED_FRAMES}")
    directions = DIRECTIONS if args.direction == "both" else (args.direction,)
    settings = {"at": args.at, "directions": list(directions), **dataclasses.asdict(protocol)}
    setup = set_up(NAME, args, settings)
    ats = args.at or [len(setup.sequence) // 2]
    for at in ats:
        if not 0 <= at < len(setup.sequence):
            raise InputError(f"--at {at}: not a frame of {setup.sequence.name} (0..{len(setup.sequence) - 1})")
    truth = truth_at_frames(setup.sequence)
    rows = [row for method in setup.configs for at in ats for direction in directions
            for row in sweep(setup, truth, method, at, direction, protocol)]
    write_csv(setup.out_dir / TRIALS_FILE, rows)
    plot(rows, protocol, setup.sequence.name).savefig(setup.out_dir / PLOT_FILE, dpi=110)
    finish(setup, summary_table(rows, protocol))


# ------------------------------------------------------------------------------------------------ trials


def tracked_results(config, camera, frames) -> list:
    """Each frame's result as the odometry reported it when it tracked the frame (what the protocol judges)."""
    return track(config, camera, frames).results


def sweep(setup: Setup, truth: dict[int, np.ndarray], method: str, at: int, direction: str, protocol: Protocol,
          tracker: Callable = tracked_results) -> list[dict]:
    """The trials of one method at one jump frame in one direction: N = step, 2 step, ... until one fails or the
    frames run out. ``tracker(config, camera, frames)`` runs a fresh odometry and gives its results (tests give a
    scripted one)."""
    rows = []
    jump = protocol.step
    while (trial := plan(at, jump, direction, protocol, len(setup.sequence), truth)) is not None:
        results = tracker(setup.configs[method], setup.sequence.camera, fed_frames(setup.sequence, trial))
        row = {"method": method, "direction": direction, "at_frame": at, "frames": jump,
               **measure(trial, results, truth, protocol)}
        rows.append(row)
        setup.say(f"{method} {direction} at {at}, {jump} frames: {row['outcome']}")
        if not row["survived"]:
            break
        jump += protocol.step
    if not rows:
        setup.say(f"{method} {direction} at {at}: no trial, a jump of {protocol.step} frames leaves the frames")
    return rows


def plan(at: int, jump: int, direction: str, protocol: Protocol, length: int,
         truth: dict[int, np.ndarray]) -> Plan | None:
    """The frames of the trial that jumps ``jump`` frames from ``at``; None once they run out."""
    start = max(0, at - protocol.warmup)
    first = at + jump + 1 if direction == "forward" else at - jump
    after = list(range(first, first + protocol.after))
    if first < start or after[-1] >= length or any(position not in truth for position in [at, *after]):
        return None
    return Plan(list(range(start, at + 1)), after)


def fed_frames(sequence, trial: Plan):
    """The trial's frames, numbered and timed on from its first frame as if no jump had happened."""
    first = trial.before[0]
    start_time = float(sequence.timestamps[first])
    interval = frame_interval(sequence)
    for k, position in enumerate(trial.before + trial.after):
        yield relabelled(sequence[position], first + k, start_time + k * interval)


def measure(trial: Plan, results: list[FrameResult], truth: dict[int, np.ndarray], protocol: Protocol) -> dict:
    """The trial's row: which frames, what the odometry did after the jump, the motion error and the outcome."""
    first, at = trial.before[0], trial.before[-1]
    # Split by the order the frames were fed, not by position: a backward jump plays some positions twice.
    fed = {first + k: position for k, position in enumerate(trial.before + trial.after)}
    jump_index = first + len(trial.before)
    before = {fed[r.frame_index]: r for r in results if r.frame_index < jump_index}
    after = {fed[r.frame_index]: r for r in results if r.frame_index >= jump_index}
    poses_before = {position: r.T_world_cam for position, r in before.items() if r.T_world_cam is not None}
    measured = next((p for p in trial.after if p in after and after[p].T_world_cam is not None), None)
    scale = _scale_before_jump(poses_before, truth)
    error = None
    if at in poses_before and scale is not None and measured is not None:
        error = frame_drop_error(poses_before[at], after[measured].T_world_cam, truth[at], truth[measured], scale)
    pair_truth = (truth[at], truth[measured if measured is not None else trial.after[0]])
    true_motion = frame_drop_error(*pair_truth, *pair_truth)  # the truth against itself: its true_* fields
    after_results = list(after.values())
    last = after.get(trial.after[-1])
    outcome = _outcome(at in poses_before and scale is not None, after_results,
                       last is not None and last.T_world_cam is not None, error, protocol)
    keyframes = sum(event.kind is EventKind.KEYFRAME_ADDED for result in before.values() for event in result.events)
    return {
        "start_frame": first,
        "next_frame": trial.after[0],
        "measured_frame": measured,
        "keyframes_before_jump": keyframes,
        "gt_translation_m": true_motion.true_translation,
        "gt_rotation_deg": true_motion.true_rotation_deg,
        "translation_m": error.translation if error else None,
        "rotation_deg": error.rotation_deg if error else None,
        "translation_error_pct": error.translation_percent if error else None,
        "rotation_error_pct": error.rotation_percent if error else None,
        "scale": scale,
        **count_events(after_results),
        "survived": outcome == "survived",
        "outcome": outcome,
    }


def _scale_before_jump(poses: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> float | None:
    """The scale of the Sim(3) alignment of the posed frames up to the jump (None when there is none)."""
    aligned = [position for position in poses if position in truth]
    if len(aligned) < MIN_ALIGNED_FRAMES:
        return None
    times = np.array(aligned, dtype=float)
    try:
        return fit_alignment(Trajectory(times, np.array([poses[p] for p in aligned])),
                             Trajectory(times, np.array([truth[p] for p in aligned])), "sim3").scale
    except InputError:  # the camera did not move before the jump: no scale
        return None


def _outcome(ready: bool, after: list[FrameResult], posed_at_end: bool, error, protocol: Protocol) -> str:
    kinds = [event.kind for result in after for event in result.events]
    failures = [i for i, kind in enumerate(kinds) if kind in FAILURES]
    recoveries = [i for i, kind in enumerate(kinds) if kind is EventKind.RECOVERY_SUCCEEDED]
    if not ready:
        return "not_ready"
    if EventKind.REINITIALIZATION in kinds:
        return "reinitialized"
    if failures and not (recoveries and recoveries[-1] > failures[-1]):
        return "unrecovered"
    if error is None or not posed_at_end:
        return "lost"
    if error.translation_percent > protocol.max_error_pct or _rotation_fails(error, protocol):
        return "error"
    return "survived"


def _rotation_fails(error, protocol: Protocol) -> bool:
    allowed = max(protocol.max_error_pct / 100.0 * error.true_rotation_deg, protocol.rotation_tolerance_deg)
    return abs(error.rotation_deg - error.true_rotation_deg) > allowed


# ----------------------------------------------------------------------------------------- table and plot


def summary_table(rows: list[dict], protocol: Protocol) -> str:
    """Each sweep's limit: the largest jump it survived, with its true motion, and what ended the sweep."""
    lines = []
    for (method, direction, at), trials in _sweeps(rows).items():
        survived = [trial for trial in trials if trial["survived"]]
        last = trials[-1]
        ended = ("frames ran out" if last["survived"]
                 else f"{last['frames']} frames ({_motion(last)}): {last['outcome']}")
        lines.append((method, direction, at, len(trials), survived[-1]["frames"] if survived else "-",
                      _motion(survived[-1]) if survived else "-", ended))
    header = ("method", "direction", "at frame", "trials", "survived up to (frames)", "true motion survived",
              "ended by")
    criteria = (f"A trial fails on a reinitialization, a failure or divergence not recovered, lost tracking, or an "
                f"error above {protocol.max_error_pct:g} % (rotation: and above {protocol.rotation_tolerance_deg:g} "
                f"deg); {protocol.after} frames after the jump, {protocol.warmup} before it.")
    return markdown_table(header, lines) + "\n\n" + criteria


def _sweeps(rows: list[dict]) -> dict[tuple, list[dict]]:
    sweeps: dict[tuple, list[dict]] = {}
    for row in rows:
        sweeps.setdefault((row["method"], row["direction"], row["at_frame"]), []).append(row)
    return sweeps


def _motion(row: dict) -> str:
    return f"{row['gt_translation_m']:.3f} m, {row['gt_rotation_deg']:.1f} deg"


def plot(rows: list[dict], protocol: Protocol, title: str):
    """FDMO Fig. 6: % error against the true motion, translation (m) and rotation (deg), a row per direction and a
    curve per method and jump frame; trials that failed marked x (at the top when nothing was measured). The
    rotation panels leave out jumps that turned less than the rotation tolerance: their % means nothing."""
    directions = [direction for direction in DIRECTIONS if any(row["direction"] == direction for row in rows)]
    canvas = figure(11, 4 * max(len(directions), 1))
    panels = canvas.subplots(max(len(directions), 1), 2, squeeze=False)
    top = 3 * protocol.max_error_pct  # errors above are drawn at the top edge
    columns = (("gt_translation_m", "translation_error_pct", "translation", "true translation [m]", 0.0),
               ("gt_rotation_deg", "rotation_error_pct", "rotation",
                f"true rotation [deg] (jumps under {protocol.rotation_tolerance_deg:g} deg left out)",
                protocol.rotation_tolerance_deg))
    for panel_row, direction in zip(panels, directions):
        sweeps = {key: trials for key, trials in _sweeps(rows).items() if key[1] == direction}
        for panel, (x_key, y_key, quantity, label, least) in zip(panel_row, columns):
            for color, ((method, _, at), trials) in enumerate(sweeps.items()):
                _curve(panel, [trial for trial in trials if trial[x_key] >= least], x_key, y_key, top, color,
                       f"{method} @ {at}")
            panel.axhline(protocol.max_error_pct, color="k", lw=0.8, ls="--")
            panel.set(xlabel=label, ylabel="% error", ylim=(0, top * 1.05), title=f"{direction} jumps: {quantity}")
            panel.legend(fontsize="small")
    canvas.suptitle(f"{title}: frame drops (x: failed; dashed: {protocol.max_error_pct:g} %)", fontsize="medium")
    return canvas


def _curve(panel, trials: list[dict], x_key: str, y_key: str, top: float, color: int, label: str) -> None:
    """One sweep: the trials survived joined by a line, those failed as x; errors above ``top`` (or none
    measured) at ``top``."""
    x = np.array([trial[x_key] for trial in trials], dtype=float)
    y = np.array([np.nan if trial[y_key] is None else trial[y_key] for trial in trials], dtype=float)
    y = np.minimum(np.nan_to_num(y, nan=top, posinf=top), top)
    survived = np.array([trial["survived"] for trial in trials], dtype=bool)
    size = 9 - 2 * (color % 3)  # methods with the same numbers stay visible under one another
    panel.plot(x[survived], y[survived], "o-", color=f"C{color}", ms=size / 2 + 2, label=label)
    panel.plot(x[~survived], y[~survived], "x", color=f"C{color}", ms=size, mew=2)
