"""Run the direct odometry (``--method direct``) on real sequences: ATE, frames tracked, timings by stage.

    python3 benchmarks/direct_real.py /work/shared/data/tum_fr3_teddy_first200 [more folders] [--frames N]

Uses the project's loaders (vo_core.datasets.open_sequence) when present, otherwise reads the three
layouts of /work/shared/data directly (TUM, KITTI odometry, VAMR). ATE is the RMSE of camera positions after
Sim(3) Umeyama alignment over the frames that got a pose (TUM ground truth associated by nearest timestamp).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from vo_core.direct.config import DirectConfig  # noqa: E402
from vo_core.direct.odometry import DirectOdometry  # noqa: E402
from vo_core.geometry.camera import PinholeCamera  # noqa: E402

TUM_FR3 = PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6)
VAMR_RATE_HZ = 10.0  # VAMR parking has no timestamps


@dataclass
class Frame:
    index: int
    timestamp: float
    image: np.ndarray
    irradiance: np.ndarray
    exposure_ms: float | None = None


def _gray(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise SystemExit(f"{path}: unreadable image")
    return image


def _quaternion_pose(t, q) -> np.ndarray:
    x, y, z, w = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _rows_3x4(path: Path) -> np.ndarray:
    rows = np.loadtxt(path, delimiter=None)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def load_local(folder: Path):
    """(camera, image paths, timestamps, ground-truth timestamps, ground-truth T_world_cam) of a folder."""
    if (folder / "rgb.txt").exists():
        entries = [line.split() for line in (folder / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
        times = np.array([float(e[0]) for e in entries])
        paths = [folder / e[1] for e in entries]
        gt = np.loadtxt(folder / "groundtruth.txt")
        return TUM_FR3, paths, times, gt[:, 0], np.array([_quaternion_pose(r[1:4], r[4:8]) for r in gt])
    if (folder / "times.txt").exists():
        K = np.loadtxt(folder / "K.txt")
        paths = sorted((folder / "image_0").glob("*.png"))
        height, width = _gray(paths[0]).shape
        camera = PinholeCamera(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        times = np.loadtxt(folder / "times.txt")[: len(paths)]
        poses = _rows_3x4(folder / "poses" / "00.txt")[: len(paths)]
        return camera, paths, times, times, poses
    if (folder / "poses.txt").exists():
        K = np.loadtxt(folder / "K.txt", delimiter=",", usecols=(0, 1, 2))
        paths = sorted((folder / "images").glob("*.png"))
        height, width = _gray(paths[0]).shape
        camera = PinholeCamera(width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        times = np.arange(len(paths)) / VAMR_RATE_HZ
        poses = _rows_3x4(folder / "poses.txt")[: len(paths)]
        return camera, paths, times, times, poses
    raise SystemExit(f"{folder}: unknown layout")


def umeyama_ate(estimated: np.ndarray, truth: np.ndarray) -> float:
    mu_e, mu_t = estimated.mean(0), truth.mean(0)
    xe, xt = estimated - mu_e, truth - mu_t
    U, D, Vt = np.linalg.svd(xt.T @ xe / len(xe))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    scale = np.trace(np.diag(D) @ S) / (xe**2).sum(1).mean()
    aligned = scale * xe @ R.T + mu_t
    return float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=1))))


def run(folder: Path, max_frames: int | None, seed: int) -> None:
    camera, paths, times, gt_times, gt_poses = load_local(folder)
    if max_frames:
        paths, times = paths[:max_frames], times[:max_frames]
    odometry = DirectOdometry(DirectConfig(), None, camera, seed)
    estimated, truth = [], []
    init_frame, tracked, keyframes, failures = None, 0, 0, 0
    stage_totals: dict[str, list[float]] = {}
    keyframe_ms, tracking_ms = [], []
    wall = time.perf_counter()
    for index, (path, timestamp) in enumerate(zip(paths, times)):
        image = _gray(path)
        result = odometry.process(Frame(index, float(timestamp), image, image.astype(np.float32)))
        failures += sum(e.kind.value == "tracking_failed" for e in result.events)
        if result.T_world_cam is None:
            continue
        tracked += 1
        if init_frame is None:
            init_frame = index
        elif "track" in result.timings_ms:
            (keyframe_ms if result.is_keyframe else tracking_ms).append(result.timings_ms["total"])
            for stage, ms in result.timings_ms.items():
                stage_totals.setdefault(stage, []).append(ms)
        keyframes += result.is_keyframe
        nearest = int(np.argmin(np.abs(gt_times - timestamp)))
        if abs(gt_times[nearest] - timestamp) < 0.02:
            estimated.append(result.T_world_cam[:3, 3])
            truth.append(gt_poses[nearest][:3, 3])
    wall = time.perf_counter() - wall
    ate = umeyama_ate(np.array(estimated), np.array(truth)) if len(estimated) > 2 else float("nan")
    print(f"{folder.name}: ATE {ate:.4f} m over {len(estimated)} poses; tracked {tracked}/{len(paths)}; "
          f"initialized at frame {init_frame}; {keyframes} keyframes; {failures} tracking failures; "
          f"{len(paths) / wall:.1f} fps overall")
    print("  ms per tracked frame by stage, mean/median: "
          + ", ".join(f"{k} {np.mean(v):.1f}/{np.median(v):.1f}" for k, v in stage_totals.items()))
    if tracking_ms:
        print(f"  non-keyframe total {np.mean(tracking_ms):.1f} ms (median {np.median(tracking_ms):.1f}), "
              f"keyframe total {np.mean(keyframe_ms) if keyframe_ms else float('nan'):.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    for folder in args.folders:
        run(folder, args.frames, args.seed)


if __name__ == "__main__":
    main()
