"""A real sequence played backward in time: the same camera and scene, motion the project was never tuned on.

    python3 benchmarks/reversed.py SOURCE OUT      # SOURCE: a TUM RGB-D or EuRoC folder; OUT: a new folder
    fdmo bench configs/bench/reversed.yaml --out results/bench_reversed

Every timestamp t becomes first + last - t (the frame intervals are kept, in reverse order), the images are linked,
not copied, and the ground truth is mirrored the same way, so `fdmo run OUT` evaluates itself as on the original.
A handheld sweep played backward starts where the original ended and meets its hard stretches in another order
and from the other side: a check on data no decision was fitted to (BENCHMARKS.md, "Real data beyond the shared
folders").
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path


def reverse_tum(source: Path, out: Path) -> None:
    """rgb.txt and groundtruth.txt mirrored (their '# file:' header kept: it names the camera), rgb/ linked."""
    images = _rows(source / "rgb.txt")
    times = [float(row[0]) for row in images]
    first, last = min(times), max(times)
    out.mkdir(parents=True, exist_ok=True)
    _link(source / "rgb", out / "rgb")
    for name, rows in (("rgb.txt", images), ("groundtruth.txt", _rows(source / "groundtruth.txt"))):
        header = [line for line in (source / name).read_text().splitlines() if line.startswith("#")]
        body = sorted((first + last - float(row[0]), row[1:]) for row in rows)
        lines = header + [f"{t:.6f} {' '.join(rest)}" for t, rest in body]
        (out / name).write_text("\n".join(lines) + "\n")


def reverse_euroc(source: Path, out: Path) -> None:
    """mav0/cam0 (the images that exist, each linked under its mirrored timestamp) and the ground truth within
    their time span, mirrored; the sensor files copied."""
    camera_in, camera_out = source / "mav0" / "cam0", out / "mav0" / "cam0"
    truth_in, truth_out = source / "mav0" / "state_groundtruth_estimate0", out / "mav0" / "state_groundtruth_estimate0"
    (camera_out / "data").mkdir(parents=True, exist_ok=True)
    truth_out.mkdir(parents=True, exist_ok=True)
    shutil.copy(camera_in / "sensor.yaml", camera_out)
    shutil.copy(truth_in / "sensor.yaml", truth_out)
    header, rows = _csv(camera_in / "data.csv")
    rows = [row for row in rows if (camera_in / "data" / row[1].strip()).is_file()]
    if not rows:
        raise SystemExit(f"{camera_in / 'data.csv'}: none of its images is in {camera_in / 'data'}")
    first, last = min(int(row[0]) for row in rows), max(int(row[0]) for row in rows)
    lines = [header]
    for row in sorted(rows, key=lambda row: first + last - int(row[0])):
        t = first + last - int(row[0])
        _link(camera_in / "data" / row[1].strip(), camera_out / "data" / f"{t}.png")
        lines.append(f"{t},{t}.png")
    (camera_out / "data.csv").write_text("\n".join(lines) + "\n")
    header, rows = _csv(truth_in / "data.csv")
    rows = sorted((first + last - int(row[0]), row[1:]) for row in rows if first <= int(row[0]) <= last)
    (truth_out / "data.csv").write_text("\n".join([header] + [",".join([str(t), *rest]) for t, rest in rows]) + "\n")


def _rows(path: Path) -> list[list[str]]:
    if not path.is_file():
        raise SystemExit(f"{path}: not found")
    return [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]


def _csv(path: Path) -> tuple[str, list[list[str]]]:
    if not path.is_file():
        raise SystemExit(f"{path}: not found")
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    return lines[0], [line.split(",") for line in lines[1:]]


def _link(target: Path, link: Path) -> None:
    if not link.exists():
        os.symlink(target.resolve(), link)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="a TUM RGB-D folder (rgb.txt) or a EuRoC folder (mav0/)")
    parser.add_argument("out", type=Path, help="the reversed folder (created)")
    args = parser.parse_args(argv)
    if (args.source / "rgb.txt").is_file():
        reverse_tum(args.source, args.out)
    elif (args.source / "mav0" / "cam0").is_dir():
        reverse_euroc(args.source, args.out)
    else:
        raise SystemExit(f"{args.source}: neither a TUM RGB-D folder (rgb.txt) nor a EuRoC one (mav0/cam0)")
    print(f"{args.out}: {args.source} played backward")
    return 0


if __name__ == "__main__":
    sys.exit(main())
