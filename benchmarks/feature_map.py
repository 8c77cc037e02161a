"""The feature map fdmo grows at direct keyframes (FDMO 4.3-4.4): its size, its reprojection error, the time it
costs per keyframe beside the window optimization's, and on synthetic sequences its 3D error against the truth.

    python3 benchmarks/feature_map.py ../shared/data/tum_fr3_teddy_first200 [more folders]
        [--synthetic smooth forward ...] [--set key=value ...]

Per run, at its end: live map points and feature keyframes, observations per point, the reprojection error of
every observation at the keyframes' (direct) poses in pixels (median and 90th percentile), and the mean and
standard deviation of the feature mapping and of the window optimization per keyframe (FDMO Table 2's
"feature-based mapping" and the direct mapping's largest part). On a synthetic sequence also the map points'
depth error: each point's depth in the first keyframe that sees it, scaled by the Sim(3) alignment of the
trajectory to the truth, against the rendered depth where it projects, relative to that depth (median, all points
and the mature ones: old enough to have been judged by the 4-of-7 rule).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.config import load_config  # noqa: E402
from vo_core.datasets import open_sequence  # noqa: E402
from vo_core.eval.metrics import evaluate  # noqa: E402
from vo_core.geometry.lie import se3_inverse, transform_points  # noqa: E402
from vo_core.synthetic import make_sequence  # noqa: E402
from vo_core.system import Odometry  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402


def run(sequence, overrides: list[str]):
    odometry = Odometry(load_config(None, [*overrides, "method=fdmo"]), sequence.camera)
    stamps, poses, mapping_ms, window_ms, frames = [], [], [], [], {}
    for frame in sequence:
        result = odometry.track(frame)
        frames[frame.index] = frame
        if "feature_mapping" in result.timings_ms:
            mapping_ms.append(result.timings_ms["feature_mapping"])
        if "window" in result.timings_ms:
            window_ms.append(result.timings_ms["window"])
        if result.T_world_cam is not None:
            stamps.append(frame.timestamp)
            poses.append(result.T_world_cam)
    metrics = evaluate(Trajectory(np.array(stamps), np.array(poses)), sequence.ground_truth)
    return odometry, metrics, np.array(mapping_ms), np.array(window_ms), frames


def reprojection_errors(odometry) -> np.ndarray:
    feature_map = odometry.features.map
    table = feature_map.observations()
    uv, _ = feature_map.pixels_of(table.keyframe, table.feature)
    errors = np.zeros(len(table))
    for frame_index in np.unique(table.keyframe):
        mine = table.keyframe == frame_index
        keyframe = feature_map.keyframes[int(frame_index)]
        points_cam = transform_points(se3_inverse(keyframe.T_world_cam), feature_map.points.position[table.point[mine]])
        errors[mine] = np.linalg.norm(odometry.camera.project(points_cam) - uv[mine], axis=1)
    return errors


def depth_errors(odometry, frames, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Relative depth error of each live point in its first observing keyframe, and whether it is mature."""
    feature_map = odometry.features.map
    table = feature_map.observations()
    first_of = {}
    for keyframe, point in zip(table.keyframe, table.point):
        first_of.setdefault(int(point), int(keyframe))
    mature_before = feature_map.newest().keyframe_id - odometry.config.features.maintenance.check_keyframes
    camera = odometry.camera
    errors, mature = [], []
    for point, frame_index in first_of.items():
        keyframe = feature_map.keyframes[frame_index]
        point_cam = transform_points(se3_inverse(keyframe.T_world_cam), feature_map.points.position[point][None])[0]
        u, v = np.round(camera.project(point_cam[None])[0]).astype(int)
        if point_cam[2] > 0 and 0 <= u < camera.width and 0 <= v < camera.height:
            truth = frames[frame_index].depth[v, u]
            errors.append(abs(point_cam[2] * scale - truth) / truth)
            mature.append(feature_map.points.first_keyframe[point] <= mature_before)
    return np.array(errors), np.array(mature)


def report(name: str, sequence, overrides: list[str], synthetic: bool) -> None:
    odometry, metrics, mapping_ms, window_ms, frames = run(sequence, overrides)
    feature_map = odometry.features.map
    errors = reprojection_errors(odometry)
    views = np.bincount(feature_map.observations().point)
    views = views[views > 0]
    line = (f"| {name} | {metrics['ate']['rmse']:.4f} | {feature_map.points.num_alive} | {len(feature_map)} | "
            f"{np.mean(views):.1f} | {np.median(errors):.2f} / {np.percentile(errors, 90):.2f} | "
            f"{mapping_ms.mean():.0f} +- {mapping_ms.std():.0f} | {window_ms.mean():.0f} +- {window_ms.std():.0f} |")
    if synthetic:
        depth, mature = depth_errors(odometry, frames, metrics["scale"])
        line += f" {np.median(depth):.2%} / {np.median(depth[mature]):.2%} |"
    print(line, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="*", type=Path)
    parser.add_argument("--synthetic", nargs="*", default=[], help="synthetic presets (640x480, 100 frames)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    print("| sequence | ATE m | points | keyframes | views per point | reprojection px median / p90 | "
          "feature mapping ms | window ms | depth error all / mature |")
    print("|---|---|---|---|---|---|---|---|---|")
    for folder in args.folders:
        report(folder.name, open_sequence(folder), args.overrides, synthetic=False)
    for preset in args.synthetic:
        report(f"synthetic {preset}", make_sequence(preset, 100, 0, 640, 480), args.overrides, synthetic=True)


if __name__ == "__main__":
    main()
