"""The files of a Rerun recording that goes on in a new file every so many frames (issue 48).

FILE.rrd holds the first part, then FILE.part2.rrd, FILE.part3.rrd, ...: each a complete .rrd (with its footer),
all of one recording (the same recording id), so that ``rerun FILE*.rrd`` opens them as one. Kept apart from the
Rerun sink, which loads rerun: the command line names these files without loading it.
"""

from __future__ import annotations

import re
from pathlib import Path

# Frames per file. The rerun SDK's file sink indexes every chunk in memory until its file is finished (the .rrd
# footer) and needs more again to write that index when the file closes; only a finished file gives it back. The
# index grows by 2-5 MiB per 1,000 frames at 20-30 frames/s (more at a slower rate: the batcher flushes by time), so
# a part of 1,000 frames holds it and its writing to a few MiB, where one file of 10,000 frames peaked 52 MiB above
# the run at its close (BENCHMARKS.md, "Long runs and determinism"); the bundled sequence (200 frames) stays one file.
PART_FRAMES = 1000


def part_path(path: Path, number: int) -> Path:
    """The file of part ``number`` (from 1) of the recording ``path``: the path itself, then PATH.partN.rrd."""
    return path if number == 1 else path.with_name(f"{path.stem}.part{number}{path.suffix}")


def recording_files(path: str | Path) -> list[Path]:
    """The files of the recording ``path`` that exist, in order: the first part, then PATH.part2.rrd, ..."""
    path = Path(path)
    return ([path] if path.is_file() else []) + later_parts(path)


def later_parts(path: Path) -> list[Path]:
    """The files PATH.partN.rrd beside ``path`` that exist, in the order of N."""
    part = re.compile(rf"{re.escape(path.stem)}\.part(\d+){re.escape(path.suffix)}")
    siblings = path.parent.iterdir() if path.parent.is_dir() else []
    numbered = sorted((int(match[1]), candidate) for candidate in siblings if (match := part.fullmatch(candidate.name)))
    return [candidate for _, candidate in numbered]


def opening_argument(files: list[Path]) -> str:
    """What to give ``rerun`` to open the recording whose ``files`` these are: the file, or all its parts (a glob)."""
    first = files[0]
    return str(first) if len(files) == 1 else str(first.with_name(f"{first.stem}*{first.suffix}"))
