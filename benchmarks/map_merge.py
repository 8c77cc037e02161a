"""A real folder played as a plan of its frames and black frames, loop closure on: does a map lost for good start
anew, and merge with the old one where the camera is back where it was (issue 49's map merging, on real images)?

    python benchmarks/map_merge.py ../shared/data/tum_fr3_teddy_first200 --plan 0-99,b30,150-199,0-199 --seeds 0 1 2

A plan is comma-separated parts played in order, numbered and timed one frame interval apart: ``A-B`` the folder's
frames A..B, ``bN`` N black frames. ``0-99,b30,150-199,0-199``: the camera covered for a second, then 50 frames on,
where the old map has no view (a new map begins, after ``fdmo.lost_frames_before_reinitialization`` lost frames), then
back over the whole folder (the old places seen again). ``0-199,b10,0-199``: covered, then back where it started
(FDMO recovers from its feature map; nothing starts anew).

For each seed: the frames posed, where a new map began, each merge (its two keyframes apart by ground truth: they
see one place, which a camera moving forward sees from metres apart; a wrong merge shows in the ATE), and the ATE
three ways: the trajectory as written (merged: one Sim(3) over all of it), the poses as tracked before any merge
moved them (one Sim(3): what the maps' different scales cost), and each map aligned on its own
(``vo_core.eval.ate_per_map``). The reference (``--clean``, another plan) is by default the folder played once
through, the ordinary run.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.experiments.common import frame_interval, relabelled, truth_at_frames  # noqa: E402
from app.experiments.two_loop import estimated_trajectory  # noqa: E402
from app.pipeline import open_dataset, track  # noqa: E402
from vo_core.config import load_config  # noqa: E402
from vo_core.errors import InputError  # noqa: E402
from vo_core.eval import evaluate  # noqa: E402
from vo_core.eval.metrics import ate_per_map  # noqa: E402
from vo_core.events import EventKind  # noqa: E402
from vo_core.geometry.lie import so3_geodesic_angle  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Part:
    first: int  # the folder's frames first..last, or -1 for black frames
    last: int
    black: int = 0


def parse_plan(text: str, length: int) -> list[Part]:
    parts = []
    for item in text.split(","):
        if item.startswith("b") and item[1:].isdigit():
            parts.append(Part(-1, -1, int(item[1:])))
            continue
        first, _, last = item.partition("-")
        if not (first.isdigit() and last.isdigit()) or not 0 <= int(first) <= int(last) < length:
            raise InputError(f"--plan {text}: '{item}' is neither A-B within 0..{length - 1} nor bN")
        parts.append(Part(int(first), int(last)))
    return parts


def played(sequence, parts: list[Part]):
    """(frames, truth): the plan's frames numbered and timed on one interval apart, and the ground truth at them."""
    frames, interval, truth = list(sequence), frame_interval(sequence), truth_at_frames(sequence)
    out, times, poses = [], [], []
    for part in parts:
        if part.black:
            out += [dataclasses.replace(frames[0], image=np.zeros_like(frames[0].image)) for _ in range(part.black)]
            continue
        for position in range(part.first, part.last + 1):
            out.append(frames[position])
            if position in truth:
                times.append(len(out) - 1)
                poses.append(truth[position])
    t0 = float(sequence.timestamps[0])
    out = [relabelled(frame, k, t0 + k * interval) for k, frame in enumerate(out)]
    return out, Trajectory(t0 + np.array(times) * interval, np.array(poses))


def run(sequence, parts: list[Part], seed: int) -> dict:
    frames, truth = played(sequence, parts)
    config = load_config(overrides=[f"seed={seed}", "features.loop_closing.enabled=true"])
    tracked = track(config, sequence.camera, frames)
    results = tracked.results
    events = [(r, e) for r in results for e in r.events]
    merged = estimated_trajectory(results, tracked.keyframe_poses)
    as_tracked = Trajectory(np.array([r.timestamp for r in results if r.T_world_cam is not None]),
                            np.array([r.T_world_cam for r in results if r.T_world_cam is not None]))
    new_maps = [r.timestamp for r, e in events if e.kind in (EventKind.INITIALIZATION_SUCCEEDED,)]
    truth_at = dict(zip(np.round(truth.timestamps, 6), truth.poses))

    def apart(details: dict) -> str:
        here = truth_at.get(round(frames[details["keyframe"]].timestamp, 6))
        there = truth_at.get(round(frames[details["merged_keyframe"]].timestamp, 6))
        if here is None or there is None:
            return "-"
        return (f"{np.linalg.norm(here[:3, 3] - there[:3, 3]):.2f} m, "
                f"{np.degrees(so3_geodesic_angle(here[:3, :3], there[:3, :3])):.0f} deg")

    return {
        "seed": seed, "frames": len(frames), "posed": len(merged.timestamps),
        "new maps at": [r.frame_index for r, e in events if e.kind is EventKind.REINITIALIZATION],
        "merges": [f"{e.details['keyframe']} -> {e.details['merged_keyframe']} ({apart(e.details)})"
                   for _, e in events if e.kind is EventKind.MAPS_MERGED],
        "ATE merged": evaluate(merged, truth)["ate"]["rmse"],
        "ATE as tracked": evaluate(as_tracked, truth)["ate"]["rmse"],
        "ATE per map": ate_per_map(as_tracked, truth, np.array(new_maps))[0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder")
    parser.add_argument("--plan", required=True)
    parser.add_argument("--clean", help="the reference plan (default: the folder once through, 0-N)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    sequence = open_dataset(args.folder, load_config().dataset)
    parts = parse_plan(args.plan, len(sequence))
    clean = args.clean or f"0-{len(sequence) - 1}"
    print(f"{sequence.name}: plan {args.plan}, clean {clean}")
    clean = parse_plan(clean, len(sequence))
    print("| seed | posed | new maps at | merges (keyframes apart by ground truth) | ATE merged | as tracked | per map "
          "| clean |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        row, reference = run(sequence, parts, seed), run(sequence, clean, seed)
        print(f"| {seed} | {row['posed']} of {row['frames']} | {row['new maps at'] or '-'} | "
              f"{'; '.join(row['merges']) or '-'} | {row['ATE merged']:.4f} | {row['ATE as tracked']:.4f} | "
              f"{row['ATE per map']:.4f} | {reference['ATE merged']:.4f} |", flush=True)


if __name__ == "__main__":
    main()
