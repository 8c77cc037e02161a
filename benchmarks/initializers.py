"""The direct system's initializers compared as paper 004 section 4 does: frames needed to initialize, the
error of the initial keyframe pair against ground truth, and the ATE of the direct run each one starts.

    python3 benchmarks/initializers.py /work/shared/data/kitti00_first100 [more folders]
        [--initializers features coarse] [--runs 5] [--length 60] [--set KEY=VALUE ...]

For each folder, ``--runs`` forward runs and as many backward runs (the reversed sequence), each from a
different start frame spread over the sequence, ``--length`` frames long. Per run and initializer:

* frames: frames fed from the run's start until the initialization succeeded (restarts included);
* rot: rotation error (deg) of the initial relative pose T_first_second against ground truth, as the frame that
  initialized reports it (after the window optimization of the first keyframe pair);
* dir: angle (deg) between the estimated and true translation directions; since the scale of a monocular
  initialization is arbitrary, the translation error normalized by the distance travelled is 2 sin(dir / 2);
* init rot / init dir: the same for the initializer's own pose, before the window optimization (paper 004's
  "initial pose that is provided by an initializer");
* ATE: RMSE (in ground-truth units) of the run's positions after Sim(3) alignment (vo_core.eval.align.umeyama),
  over the frames that got a pose.

Ground truth is matched to a frame by the nearest timestamp (within 20 ms); runs whose start has no ground
truth near it are skipped for the pose errors.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.config import load_config  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.direct.odometry import DirectOdometry  # noqa: E402
from vo_core.eval.align import umeyama  # noqa: E402
from vo_core.events import EventKind  # noqa: E402
from vo_core.geometry.lie import se3_inverse, so3_log  # noqa: E402

MAX_DT_S = 0.02


@dataclass
class RunResult:
    frames: int | None  # None: never initialized
    rotation_deg: float = np.nan
    direction_deg: float = np.nan
    init_rotation_deg: float = np.nan
    init_direction_deg: float = np.nan
    ate: float = np.nan
    model: str = "-"
    tracked: int = 0


def ground_truth_pose(sequence, timestamp: float) -> np.ndarray | None:
    truth = sequence.ground_truth
    k = int(np.argmin(np.abs(truth.timestamps - timestamp)))
    return truth.poses[k] if abs(truth.timestamps[k] - timestamp) <= MAX_DT_S else None


def relative_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    rotation = float(np.degrees(np.linalg.norm(so3_log(T_true[:3, :3].T @ T_est[:3, :3]))))
    a, b = T_est[:3, 3], T_true[:3, 3]
    cosine = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
    return rotation, float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))


class RecordingOdometry(DirectOdometry):
    """Keeps the first initialization's relative pose as the initializer handed it over."""

    initial_T_first_second: np.ndarray | None = None

    def _start_from_initialization(self, frame, pyramid, outcome, result):
        if self.initial_T_first_second is None:
            self.initial_T_first_second = outcome.T_first_second.copy()
        super()._start_from_initialization(frame, pyramid, outcome, result)


def run(sequence, initializer: str, overrides: list[str]) -> RunResult:
    config = load_config(None, [*overrides, "method=direct", f"direct.initializer={initializer}"])
    odometry = RecordingOdometry(config.direct, config.init, sequence.camera, config.seed)
    outcome = RunResult(frames=None)
    timestamps, estimated, truth = {}, [], []
    for count, frame in enumerate(sequence, start=1):
        result = odometry.process(frame)
        timestamps[frame.index] = frame.timestamp
        for event in result.events:
            if event.kind is EventKind.INITIALIZATION_SUCCEEDED and outcome.frames is None:
                outcome.frames = count
                outcome.model = str(event.details.get("model", "-"))
                first_true = ground_truth_pose(sequence, timestamps[event.details["first_frame"]])
                here_true = ground_truth_pose(sequence, frame.timestamp)
                if first_true is not None and here_true is not None:
                    T_true = se3_inverse(first_true) @ here_true
                    T_est = se3_inverse(np.asarray(event.details["first_T_world_cam"])) @ result.T_world_cam
                    outcome.rotation_deg, outcome.direction_deg = relative_errors(T_est, T_true)
                    outcome.init_rotation_deg, outcome.init_direction_deg = relative_errors(
                        odometry.initial_T_first_second, T_true
                    )
        if result.T_world_cam is not None:
            T_true = ground_truth_pose(sequence, frame.timestamp)
            if T_true is not None:
                estimated.append(result.T_world_cam[:3, 3])
                truth.append(T_true[:3, 3])
    outcome.tracked = len(estimated)
    if len(estimated) > 2 and np.ptp(np.array(estimated), axis=0).max() > 0:
        source, target = np.array(estimated), np.array(truth)
        R, t, s = umeyama(source, target, with_scale=True)
        outcome.ate = float(np.sqrt(np.mean(np.sum((source @ R.T * s + t - target) ** 2, axis=1))))
    return outcome


def runs_of(folder: Path, count: int, length: int):
    """(label, sequence) of ``count`` forward and ``count`` backward runs from spread start frames."""
    full = open_sequence(folder)
    length = min(length, len(full))
    starts = np.linspace(0, len(full) - length, count).round().astype(int)
    for direction, sequence in (("fwd", full), ("bwd", full.reversed())):
        for start in starts:
            yield f"{direction}@{start}", sequence.cut(start=int(start), end=int(start) + length)


def summarize(name: str, results: list[RunResult]) -> str:
    done = [r for r in results if r.frames is not None]
    if not done:
        return f"  {name}: never initialized in {len(results)} runs"

    def median(values):
        values = [v for v in values if np.isfinite(v)]
        return f"{np.median(values):.4g}" if values else "n/a"

    return (
        f"  {name}: initialized {len(done)}/{len(results)}; frames mean {np.mean([r.frames for r in done]):.1f}; "
        f"median rot {median(r.rotation_deg for r in done)} deg, dir {median(r.direction_deg for r in done)} deg "
        f"(initializer's own: rot {median(r.init_rotation_deg for r in done)} deg, "
        f"dir {median(r.init_direction_deg for r in done)} deg); "
        f"median ATE {median(r.ate for r in done)}; mean ATE {np.nanmean([r.ate for r in done]):.4f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--initializers", nargs="+", default=["features", "coarse"])
    parser.add_argument("--runs", type=int, default=5, help="forward runs (and as many backward)")
    parser.add_argument("--length", type=int, default=60, help="frames per run")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    for folder in args.folders:
        results: dict[str, list[RunResult]] = {name: [] for name in args.initializers}
        print(f"{folder.name}:")
        for label, sequence in runs_of(folder, args.runs, args.length):
            line = [f"  {label:>8}"]
            for name in args.initializers:
                r = run(sequence, name, args.overrides)
                results[name].append(r)
                line.append(
                    f"{name} frames {r.frames} {r.model} rot {r.rotation_deg:.2f} dir {r.direction_deg:.1f} "
                    f"(init rot {r.init_rotation_deg:.2f} dir {r.init_direction_deg:.1f}) "
                    f"ATE {r.ate:.4f} tracked {r.tracked}"
                )
            print(" | ".join(line), flush=True)
        for name in args.initializers:
            print(summarize(name, results[name]))


if __name__ == "__main__":
    main()
