"""Plot an estimated trajectory against ground truth after alignment: a top view and x, y, z over time (PNG).

    python3 benchmarks/plot_trajectory.py results/latest/trajectory.tum GT.txt --out trajectory.png
    python3 benchmarks/plot_trajectory.py est.tum gt.txt --align se3 --plane xz

Both files may be TUM, KITTI or EuRoC CSV (vo_core.trajectory). Poses are matched by timestamp and the
alignment (Umeyama, Sim(3) by default) is fitted on the matched positions, then applied to the whole estimate,
so frames without ground truth are drawn too; the ground truth is drawn over the estimate's time span. The top
view is the plane of the ground truth's two largest extents unless --plane names one (KITTI's camera world is
y-down: its ground plane is xz).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.errors import InputError  # noqa: E402
from vo_core.eval import ALIGNMENTS, DEFAULT_MAX_DT_S, associate, evaluate, fit_alignment  # noqa: E402
from vo_core.trajectory import Trajectory, read_trajectory  # noqa: E402

AXES = "xyz"
PLANES = ("xy", "xz", "yz")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("estimate", type=Path, help="trajectory file (TUM, KITTI or EuRoC CSV)")
    parser.add_argument("ground_truth", type=Path, help="trajectory file (TUM, KITTI or EuRoC CSV)")
    parser.add_argument("--align", choices=ALIGNMENTS, default="sim3")
    parser.add_argument("--max-dt", type=float, default=DEFAULT_MAX_DT_S, help="association tolerance (s)")
    parser.add_argument("--plane", choices=PLANES, help="top-view plane (default: the ground truth's widest)")
    parser.add_argument("--out", type=Path, help="PNG path (default: beside the estimate, <name>.png)")
    args = parser.parse_args()
    try:
        estimate, ground_truth = read_trajectory(args.estimate), read_trajectory(args.ground_truth)
        matched_estimate, matched_truth = associate(estimate, ground_truth, args.max_dt)
        aligned = fit_alignment(matched_estimate, matched_truth, args.align).apply(estimate)
        metrics = evaluate(estimate, ground_truth, align=args.align, max_dt=args.max_dt)
    except InputError as error:
        print(f"plot_trajectory: error: {error}", file=sys.stderr)
        return 2
    out = args.out or args.estimate.with_suffix(".png")
    ground_truth = during(ground_truth, estimate, args.max_dt)
    title = (f"{args.estimate.name} vs {args.ground_truth.name}: ATE rmse {metrics['ate']['rmse']:.4f} m over "
             f"{metrics['matched_poses']} poses ({args.align}, scale {metrics['scale']:.3f})")
    plot(aligned, ground_truth, args.plane or widest_plane(ground_truth), title).savefig(out, dpi=120)
    print(f"{title}\nwrote {out}")
    return 0


def during(ground_truth: Trajectory, estimate: Trajectory, margin_s: float) -> Trajectory:
    """The ground truth over the estimate's time span only (a run often covers a part of a sequence)."""
    first, last = estimate.timestamps[0] - margin_s, estimate.timestamps[-1] + margin_s
    return ground_truth.subset(np.flatnonzero((ground_truth.timestamps >= first) & (ground_truth.timestamps <= last)))


def widest_plane(ground_truth: Trajectory) -> str:
    """The plane of the two axes along which the ground truth extends most (the ground for most datasets)."""
    extents = np.ptp(ground_truth.positions, axis=0)
    first, second = sorted(np.argsort(extents)[-2:])
    return AXES[first] + AXES[second]


def plot(aligned_estimate: Trajectory, ground_truth: Trajectory, plane: str, title: str) -> plt.Figure:
    figure = plt.figure(figsize=(13, 6), layout="constrained")
    left, right = figure.subfigures(1, 2, width_ratios=[1, 1.2])
    view = left.subplots()
    u, v = (AXES.index(axis) for axis in plane)
    view.plot(ground_truth.positions[:, u], ground_truth.positions[:, v], "k-", lw=1, label="ground truth")
    view.plot(aligned_estimate.positions[:, u], aligned_estimate.positions[:, v], "C0-", lw=1, label="estimate")
    view.plot(*ground_truth.positions[0, [u, v]], "ko", ms=4, label="start")
    view.set(xlabel=f"{plane[0]} [m]", ylabel=f"{plane[1]} [m]", aspect="equal", title=f"top view ({plane})")
    view.legend(loc="best", fontsize="small")
    start = ground_truth.timestamps[0]
    for axis_index, axis in enumerate(right.subplots(3, 1, sharex=True)):
        axis.plot(ground_truth.timestamps - start, ground_truth.positions[:, axis_index], "k-", lw=1)
        axis.plot(aligned_estimate.timestamps - start, aligned_estimate.positions[:, axis_index], "C0-", lw=1)
        axis.set_ylabel(f"{AXES[axis_index]} [m]")
    axis.set_xlabel("time since the first ground-truth pose [s]")
    figure.suptitle(title, fontsize="medium")
    return figure


if __name__ == "__main__":
    sys.exit(main())
