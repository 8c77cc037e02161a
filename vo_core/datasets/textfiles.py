"""Reading the small text files of dataset layouts, with one-line errors that name the file and the line.

Every layout has the same needs: a table of numbers (timestamps, poses, intrinsics) with ``#`` comments and
comma or space separators, a YAML file (possibly with OpenCV's ``%YAML:1.0`` header, as EuRoC writes it),
and timestamps that must increase. Malformed input raises ``InputError``; nothing here guesses.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

from vo_core.errors import InputError
from vo_core.yaml_input import parse_yaml

_SEPARATORS = re.compile(r"[,\s]+")


def require_file(path: Path, what: str) -> Path:
    """``path`` if it is a file, else an InputError saying which ``what`` is missing."""
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    return path


def read_text(path: Path) -> str:
    """The text of a file; InputError when it cannot be read or is not UTF-8 text."""
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read ({error.__class__.__name__})") from None


def text_lines(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of the non-empty, non-comment lines of a text file."""
    numbered = ((number, line.strip()) for number, line in enumerate(read_text(path).splitlines(), start=1))
    return [(number, line) for number, line in numbered if line and not line.startswith("#")]


def split_fields(line: str) -> list[str]:
    """The fields of a line separated by commas and/or whitespace."""
    return [field for field in _SEPARATORS.split(line.strip()) if field]


def parse_numbers(path: Path, line_number: int, fields: list[str], count: int | None = None) -> np.ndarray:
    """``fields`` as floats; ``count`` (if given) is the number expected. Non-numbers raise InputError."""
    if count is not None and len(fields) < count:
        raise InputError(f"{path}:{line_number}: expected {count} numbers, found {len(fields)}")
    try:
        values = np.array([float(field) for field in (fields if count is None else fields[:count])])
    except ValueError:
        raise InputError(f"{path}:{line_number}: not a number in '{' '.join(fields)}'") from None
    return values


def read_table(path: Path, columns: int, allow_nan: bool = False) -> np.ndarray:
    """(N, columns) floats: the first ``columns`` numbers of every data line (extra columns are ignored).

    Non-finite values are refused unless ``allow_nan`` (TUM monoVO's groundtruthSync.txt marks frames without
    ground truth with NaN)."""
    rows = []
    for number, line in text_lines(require_file(path, "file")):
        values = parse_numbers(path, number, split_fields(line), columns)
        if not allow_nan and not np.all(np.isfinite(values)):
            raise InputError(f"{path}:{number}: non-finite value")
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: no data lines")
    return np.array(rows)


def read_matrix(path: Path, rows: int, cols: int) -> np.ndarray:
    """A rows x cols matrix written as rows lines (VAMR/KITTI K.txt), comma or space separated."""
    values = read_table(path, cols)
    if values.shape[0] != rows:
        raise InputError(f"{path}: expected a {rows}x{cols} matrix, found {values.shape[0]} rows")
    return values


def read_yaml(path: Path) -> dict[str, Any]:
    """A YAML mapping. OpenCV's ``%YAML:1.0`` directive (EuRoC's sensor.yaml) is not YAML 1.1: it is skipped."""
    text = read_text(require_file(path, "YAML file"))
    text = re.sub(r"^%YAML:1\.0\s*\n", "", text)
    content = parse_yaml(text, str(path))
    if not isinstance(content, dict):
        raise InputError(f"{path}: expected a YAML mapping of keys to values")
    return content


def check_increasing(timestamps: np.ndarray, path: Path, line_numbers=None) -> None:
    """Timestamps must be finite and strictly increasing; the first offender is named by its line in ``path``
    (``line_numbers``: the line of each timestamp, where they were read from lines), else by its position (the
    names of a folder's images, a video's frames)."""
    timestamps = np.asarray(timestamps, dtype=float)

    def offender(index: int) -> tuple[str, str]:  # (where, what): "file:line", "" or "file", " at entry N"
        return (f"{path}:{line_numbers[index]}", "") if line_numbers is not None else (str(path), f" at entry {index}")

    if not np.all(np.isfinite(timestamps)):
        where, entry = offender(int(np.argmin(np.isfinite(timestamps))))
        raise InputError(f"{where}: non-finite timestamp{entry}")
    steps = np.diff(timestamps)
    if np.any(steps <= 0):
        bad = int(np.argmax(steps <= 0)) + 1
        kind = "duplicated" if steps[bad - 1] == 0 else "out of order"
        where, entry = offender(bad)
        raise InputError(f"{where}: timestamp {timestamps[bad]:.9f}{entry} is {kind}")


def data_line_numbers(path: Path) -> list[int]:
    """The line number of each row ``read_table`` reads from ``path``."""
    return [number for number, _ in text_lines(path)]
