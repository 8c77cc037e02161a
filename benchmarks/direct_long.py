"""Long runs: every shared folder played forward then backward as one sequence, and the synthetic presets at
1,000 frames, over several seeds, optionally beside DSO run on the very same images.

    python3 benchmarks/direct_long.py ../shared/data/tum_fr3_teddy_first200 [more folders]
        [--synthetic smooth forward planar] [--frames 1000] [--seeds 0 1 2 3 4] [--set KEY=VALUE ...]
        [--dso PATH/TO/dso_headless --dso-runs 3 --work DIR]

It runs the configured method (fdmo unless ``--set method=direct``; ``--no-fdmo``: none, DSO only).

A folder of N frames becomes a sequence of 2N - 1 frames: 0 .. N-1, then N-2 .. 0, renumbered and re-timed so
that indices and timestamps increase (the median frame period of the folder); its ground truth is the folder's
pose of each original frame at the new timestamps (nearest within 20 ms). The frames are the project's
rectified images, so DSO, when asked, sees the same pixels: they are written as PNGs with a list of
``path timestamp`` lines and a DSO camera file (Pinhole, no distortion, "none"), its poses read back and
evaluated the same way (vo_core.eval, Sim(3)-aligned ATE over the frames that got a pose). DSO needs an image
size it can halve repeatedly, so images are cropped on the right and bottom to a multiple of 16 with K
unchanged (KITTI 1241x376 -> 1232x368, as ../shared/peers/README.md says; the project runs the full image).

DSO is built from its public source outside the repository (../shared/peers/README.md); ``dso_headless`` is a
small main around FullSystem::addActiveFrame with the settings of PEERS.md (mode=1, preset 0, linearized
operation), writing every frame's pose (non-keyframes relative to their keyframe's final pose).
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from direct_real import print_spread, run_sequence  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.eval.metrics import evaluate  # noqa: E402
from vo_core.synthetic import make_sequence  # noqa: E402
from vo_core.trajectory import Trajectory, read_trajectory  # noqa: E402

MAX_DT_S = 0.02
DSO_SIZE_MULTIPLE = 16  # DSO's pyramid halves the image down to its coarsest level


class Palindrome:
    """A sequence played forward then backward, renumbered and re-timed to increase throughout."""

    def __init__(self, sequence):
        self.source = sequence
        count = len(sequence)
        self.positions = np.concatenate([np.arange(count), np.arange(count - 2, -1, -1)])
        period = float(np.median(np.diff(sequence.timestamps))) if count > 1 else 0.1
        self.timestamps = sequence.timestamps[0] + period * np.arange(len(self.positions))
        self.camera = sequence.camera
        self.name = f"{sequence.name} forward+backward"
        self.ground_truth = self._ground_truth(sequence)

    def __len__(self) -> int:
        return len(self.positions)

    def __iter__(self):
        for index, (position, timestamp) in enumerate(zip(self.positions, self.timestamps)):
            yield dataclasses.replace(self.source[int(position)], index=index, timestamp=float(timestamp))

    def _ground_truth(self, sequence) -> Trajectory | None:
        truth = sequence.ground_truth
        if truth is None:
            return None
        original = sequence.timestamps[self.positions]
        nearest = np.abs(truth.timestamps[None, :] - original[:, None]).argmin(axis=1)
        close = np.abs(truth.timestamps[nearest] - original) <= MAX_DT_S
        return Trajectory(self.timestamps[close], truth.poses[nearest[close]])


def sequences(folders: list[Path], presets: list[str], frames: int):
    for folder in folders:
        yield Palindrome(open_sequence(folder))
    for preset in presets:
        sequence = make_sequence(preset, frames, 0)
        sequence.name = f"synthetic {preset} ({frames} frames)"
        yield sequence


def export_for_dso(sequence, directory: Path) -> tuple[Path, Path]:
    """The frames as PNGs (cropped to DSO's size), their list and the camera file."""
    directory.mkdir(parents=True, exist_ok=True)
    camera = sequence.camera
    width = camera.width // DSO_SIZE_MULTIPLE * DSO_SIZE_MULTIPLE
    height = camera.height // DSO_SIZE_MULTIPLE * DSO_SIZE_MULTIPLE
    lines = []
    for frame in sequence:
        path = directory / f"{frame.index:06d}.png"
        if not path.exists():
            cv2.imwrite(str(path), frame.image[:height, :width])
        lines.append(f"{path} {frame.timestamp:.9f}")
    listing, calibration = directory / "images.txt", directory / "camera.txt"
    listing.write_text("\n".join(lines) + "\n")
    calibration.write_text(
        f"Pinhole {camera.fx} {camera.fy} {camera.cx} {camera.cy} 0\n{width} {height}\nnone\n{width} {height}\n"
    )
    return listing, calibration


def run_dso(binary: Path, sequence, work: Path, runs: int) -> list[float]:
    listing, calibration = export_for_dso(sequence, work / re.sub(r"\W+", "_", sequence.name))
    ates = []
    for attempt in range(runs):
        poses = listing.parent / f"dso_poses_{attempt}.tum"
        stdout = subprocess.run([str(binary), str(listing), str(calibration), str(poses)], capture_output=True,
                                text=True, check=True).stdout
        output = next((line for line in stdout.splitlines() if line.startswith("frames ")), "")
        estimate = read_trajectory(poses, "tum")
        ate = evaluate(estimate, sequence.ground_truth)["ate"]["rmse"] if len(estimate) > 2 else float("nan")
        print(f"{sequence.name}: DSO run {attempt}: ATE {ate:.4f} m; {output}", flush=True)
        ates.append(ate)
    return ates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="*", type=Path)
    parser.add_argument("--synthetic", nargs="*", default=[], help="synthetic presets")
    parser.add_argument("--frames", type=int, default=1000, help="frames of a synthetic preset")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--dso", type=Path, help="a dso_headless binary: run DSO on the same frames too")
    parser.add_argument("--dso-runs", type=int, default=3)
    parser.add_argument("--work", type=Path, default=Path("/tmp/fdmo_long_runs"), help="DSO's frames and poses")
    parser.add_argument("--no-fdmo", action="store_true", help="only DSO")
    args = parser.parse_args()
    for sequence in sequences(args.folders, args.synthetic, args.frames):
        if not args.no_fdmo:
            ates = [run_sequence(sequence.name, sequence, sequence.ground_truth, [*args.overrides, f"seed={seed}"])
                    for seed in args.seeds]
            print_spread(sequence.name, args.seeds, ates)
        if args.dso:
            ates = run_dso(args.dso, sequence, args.work, args.dso_runs)
            print(f"{sequence.name}: DSO over {args.dso_runs} runs: median {np.median(ates):.4f}, "
                  f"min {np.min(ates):.4f}, max {np.max(ates):.4f} m", flush=True)


if __name__ == "__main__":
    main()
