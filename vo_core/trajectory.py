"""Timestamped poses: the one trajectory type used for estimates and ground truth alike, and its files.

Poses are ``T_world_cam`` (camera-to-world, 4x4); timestamps are in seconds.

Three file formats are read and written (``FORMATS``):

- ``"tum"``: TUM RGB-D (Sturm et al. 2012), a line ``timestamp tx ty tz qx qy qz qw`` per pose, seconds,
  space or comma separated, ``#`` comments. Written with ``%.9f`` (nanoseconds, nanometres).
- ``"kitti"``: KITTI odometry, 12 numbers per line, the top 3x4 of the pose row-major. The file has no
  timestamps: see ``read_trajectory``.
- ``"euroc"``: the ASL CSV of EuRoC (``#timestamp [ns],p_RS_R_x,p_RS_R_y,p_RS_R_z,q_RS_w,q_RS_x,q_RS_y,q_RS_z``,
  further columns such as velocities and biases ignored); nanoseconds become seconds. A float64 second holds
  a 2014 epoch time to ~0.2 microseconds, so writing back may move a nanosecond stamp by that much.

Quaternions are normalized and rotation matrices projected onto SO(3) when read: files written with few
decimals still give exact rotations. A TUM or EuRoC line whose pose is all NaN (TUM monoVO's groundtruthSync.txt
marks frames without ground truth so) is no pose and is skipped. Malformed lines, non-finite values and
timestamps that do not increase raise ``InputError`` naming the file and line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from vo_core.errors import InputError


@dataclass
class Trajectory:
    timestamps: np.ndarray  # (N,) seconds, strictly increasing
    poses: np.ndarray  # (N, 4, 4) T_world_cam

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=float).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=float).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise ValueError(f"{len(self.timestamps)} timestamps but {len(self.poses)} poses")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) camera centres in the world frame."""
        return self.poses[:, :3, 3]

    def subset(self, indices: np.ndarray) -> "Trajectory":
        return Trajectory(self.timestamps[indices], self.poses[indices])

    def within(self, first: float, last: float) -> "Trajectory":
        """The poses timed ``first`` to ``last`` seconds, both included."""
        return self.subset(np.flatnonzero((self.timestamps >= first) & (self.timestamps <= last)))


def loop_corrected(correction: dict, timestamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) moved by a loop closure or a map merge, ``correction`` being its LOOP_CLOSED or MAPS_MERGED
    event's details: a pose of the map it moved (timed within one of its ``segments``, [start, end or None]) moves
    with the keyframe before it, the one it was tracked from: keyframe k (timed ``keyframe_times[k]``, increasing)
    has the correction ``corrections[k]`` (16 numbers, a 4x4 similarity world -> world), which takes a pose T to C T,
    the scale dropped from its rotation. Poses of other maps stay; a pose before the first keyframe moves with it."""
    keyframe_times = np.asarray(correction["keyframe_times"], dtype=float)
    corrections = np.asarray(correction["corrections"], dtype=float).reshape(-1, 4, 4)
    timestamps = np.asarray(timestamps, dtype=float)
    poses = np.array(poses, dtype=float).reshape(-1, 4, 4)
    spans = np.array([[start, np.inf if end is None else end] for start, end in correction["segments"]]).reshape(-1, 2)
    mine = np.any((timestamps[:, None] >= spans[:, 0]) & (timestamps[:, None] < spans[:, 1]), axis=1)
    keyframe = np.clip(np.searchsorted(keyframe_times, timestamps[mine], side="right") - 1, 0, None)
    moved = corrections[keyframe] @ poses[mine]
    scales = np.linalg.norm(moved[:, :3, 0], axis=1)  # a similarity's columns have its scale as their norm
    moved[:, :3, :3] /= scales[:, None, None]
    poses[mine] = moved
    return poses


FORMATS = ("tum", "kitti", "euroc")
KITTI_FRAME_PERIOD_S = 0.1  # KITTI's cameras run at 10 Hz: the stand-in timestamps without a times.txt
NUMBER_FORMAT = "%.9f"  # nanosecond timestamps and nanometre positions in TUM and KITTI files
NS_PER_S = 1_000_000_000
# A 3x3 block farther than this (Frobenius norm of R R^T - I) from a rotation is refused rather than projected:
# it is a wrong file, not a rounded one (a matrix written with 4 decimals is ~1e-4 off).
ROTATION_TOLERANCE = 1e-2

_FIELDS_PER_LINE = {"tum": 8, "kitti": 12, "euroc": 8}  # EuRoC: at least 8, more are ignored
_SEPARATORS = re.compile(r"[,\s]+")
_EUROC_HEADER = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
# A time this large is nanoseconds (EuRoC, ROS), not seconds: 1e12 s after 1970 is the year 33658.
MIN_NANOSECOND_TIMESTAMP = 1e12


# ------------------------------------------------------------------------------------------------ reading


def read_trajectory(path: str | Path, format: str | None = None, timestamps: np.ndarray | None = None) -> Trajectory:
    """The trajectory in ``path``; ``format`` is one of ``FORMATS``, or None to detect it (``detect_format``).

    KITTI files have no timestamps. They come from ``timestamps`` if given, else from a ``times.txt`` beside
    the file or, for a file in a ``poses/`` folder, beside that folder (one time in seconds per line, as in
    KITTI's sequence folders and the layout the KITTI loader reads), else they are the line index times 0.1 s
    (KITTI's 10 Hz). ``timestamps`` is ignored for the other formats, which carry their own.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: trajectory file not found")
    format = detect_format(path) if format is None else _checked_format(format)
    rows = _data_rows(path)
    if format == "kitti":
        return Trajectory(_kitti_timestamps(path, len(rows), timestamps), _poses_from_matrices(rows, path))
    trajectory = _from_timestamped_quaternions(rows, path, format)
    _check_increasing(trajectory.timestamps, path, rows.line_numbers)
    return trajectory


def detect_format(path: Path) -> str:
    """The format of a trajectory file: by extension (``.tum``, ``.kitti``, ``.csv`` for EuRoC), else by content:
    a header naming nanoseconds or ``q_RS`` is EuRoC, 12 numbers a line KITTI, 8 numbers TUM, more than 8 with
    a nanosecond-sized first column EuRoC (an ASL state file)."""
    suffix = path.suffix.lower()
    if suffix in (".tum", ".kitti"):
        return suffix[1:]
    if suffix == ".csv":
        return "euroc"
    header, first = _first_lines(path)
    if "[ns]" in header or "q_RS" in header:
        return "euroc"
    fields = _split(first)
    if len(fields) == _FIELDS_PER_LINE["kitti"]:
        return "kitti"
    if len(fields) == _FIELDS_PER_LINE["tum"]:
        return "tum"
    if len(fields) > _FIELDS_PER_LINE["euroc"] and _looks_like_nanoseconds(fields[0]):
        return "euroc"
    raise InputError(f"{path}: cannot tell the trajectory format ({len(fields)} numbers a line; TUM has 8, KITTI 12)")


def _checked_format(format: str) -> str:
    if format not in FORMATS:
        raise InputError(f"unknown trajectory format '{format}' (known: {', '.join(FORMATS)})")
    return format


def _first_lines(path: Path) -> tuple[str, str]:
    """The comment lines before the data (joined) and the first data line."""
    comments = []
    for line in _read_text(path).splitlines():
        stripped = line.strip()
        if stripped.startswith("#"):
            comments.append(stripped)
        elif stripped:
            return " ".join(comments), stripped
    raise InputError(f"{path}: no data lines")


def _looks_like_nanoseconds(field: str) -> bool:
    try:
        return float(field) >= MIN_NANOSECOND_TIMESTAMP
    except ValueError:
        return False


@dataclass
class _Rows:
    """The numbers of the data lines of a file, and each line's number for error messages."""

    values: list[list[str]]
    line_numbers: list[int]

    def __len__(self) -> int:
        return len(self.values)

    def subset(self, keep: np.ndarray) -> "_Rows":
        indices = np.flatnonzero(keep)
        return _Rows([self.values[i] for i in indices], [self.line_numbers[i] for i in indices])


def _data_rows(path: Path) -> _Rows:
    rows = _Rows([], [])
    for number, line in enumerate(_read_text(path).splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            rows.values.append(_split(stripped))
            rows.line_numbers.append(number)
    if not rows:
        raise InputError(f"{path}: no data lines")
    return rows


def _read_text(path: Path) -> str:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read ({error.__class__.__name__})") from None


def _split(line: str) -> list[str]:
    return [field for field in _SEPARATORS.split(line) if field]


def _numbers(rows: _Rows, path: Path, count: int, exact: bool, first_column_ns: bool = False) -> np.ndarray:
    """(N, count) floats. Each line must hold ``count`` numbers (at least ``count`` unless ``exact``).

    With ``first_column_ns`` the first column, integer nanoseconds, becomes seconds without passing through a
    float of 19 digits (which would round it to ~256 ns before the division)."""
    table = np.empty((len(rows), count))
    for row, (fields, number) in enumerate(zip(rows.values, rows.line_numbers)):
        if len(fields) < count or (exact and len(fields) > count):
            expected = f"{count}" if exact else f"at least {count}"
            raise InputError(f"{path}:{number}: expected {expected} numbers, found {len(fields)}")
        try:
            table[row] = [float(field) for field in fields[:count]]
            if first_column_ns:
                table[row, 0] = seconds_from_nanoseconds(fields[0])
        except ValueError:
            raise InputError(f"{path}:{number}: not a number in '{' '.join(fields)}'") from None
    return table


def _check_finite(table: np.ndarray, rows: _Rows, path: Path) -> None:
    bad = np.flatnonzero(~np.all(np.isfinite(table), axis=1))
    if len(bad):
        raise InputError(f"{path}:{rows.line_numbers[bad[0]]}: non-finite value in '{' '.join(rows.values[bad[0]])}'")


def seconds_from_nanoseconds(field: str) -> float:
    """An integer count of nanoseconds, as written, in seconds: whole seconds and the rest apart, so that a
    19-digit count does not pass through a double (which would round it to ~256 ns)."""
    try:
        whole_seconds, nanoseconds = divmod(int(field), NS_PER_S)
        return whole_seconds + nanoseconds / NS_PER_S
    except (ValueError, OverflowError):  # written as a float ("1.4e18"): its precision is already gone
        return float(field) / NS_PER_S


def _from_timestamped_quaternions(rows: _Rows, path: Path, format: str) -> Trajectory:
    euroc = format == "euroc"
    table = _numbers(rows, path, _FIELDS_PER_LINE[format], exact=not euroc, first_column_ns=euroc)
    # TUM monoVO's groundtruthSync.txt has a line for every frame, all NaN where no pose is known: not a pose.
    known = ~np.all(np.isnan(table[:, 1:]), axis=1) & np.isfinite(table[:, 0])
    if not np.any(known):
        raise InputError(f"{path}: no line has a pose (all NaN)")
    table, rows = table[known], rows.subset(known)
    _check_finite(table, rows, path)
    timestamps, positions = table[:, 0], table[:, 1:4]
    # TUM stores (qx, qy, qz, qw), EuRoC (qw, qx, qy, qz); scipy wants (x, y, z, w).
    quaternions_xyzw = table[:, [5, 6, 7, 4]] if euroc else table[:, 4:8]
    largest = np.max(np.abs(quaternions_xyzw), axis=1)
    if np.any(largest < 1e-9):  # cannot be normalized: no rotation at all
        bad = int(np.argmax(largest < 1e-9))
        raise InputError(f"{path}:{rows.line_numbers[bad]}: zero quaternion")
    scaled = quaternions_xyzw / largest[:, None]  # first: the norm of (1e160, 0, 0, 1) would overflow
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(scaled / np.linalg.norm(scaled, axis=1)[:, None]).as_matrix()
    poses[:, :3, 3] = positions
    return Trajectory(timestamps, poses)


def _poses_from_matrices(rows: _Rows, path: Path) -> np.ndarray:
    table = _numbers(rows, path, _FIELDS_PER_LINE["kitti"], exact=True)
    _check_finite(table, rows, path)
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :] = table.reshape(-1, 3, 4)
    rotations = poses[:, :3, :3]
    deviation = np.linalg.norm(rotations @ rotations.transpose(0, 2, 1) - np.eye(3), axis=(1, 2))
    not_rotations = (deviation > ROTATION_TOLERANCE) | (np.linalg.det(rotations) <= 0)
    if np.any(not_rotations):
        bad = int(np.argmax(not_rotations))
        raise InputError(f"{path}:{rows.line_numbers[bad]}: the 3x3 block is not a rotation matrix")
    poses[:, :3, :3] = nearest_rotations(rotations)
    return poses


def nearest_rotations(matrices: np.ndarray) -> np.ndarray:
    """(N, 3, 3) the rotations closest in Frobenius norm to (N, 3, 3) matrices: U V^T of their SVD, with the
    sign of the last singular vector chosen to keep det = +1 (the orthogonal Procrustes solution)."""
    U, _, Vt = np.linalg.svd(matrices)
    signs = np.ones((len(matrices), 3))
    signs[:, 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * signs[:, None, :]) @ Vt


def _kitti_timestamps(path: Path, count: int, timestamps: np.ndarray | None) -> np.ndarray:
    if timestamps is not None:
        timestamps = np.asarray(timestamps, dtype=float).reshape(-1)
        if len(timestamps) != count:
            raise InputError(f"{path}: {count} poses but {len(timestamps)} timestamps given")
        _check_increasing(timestamps, path, line_numbers=None)
        return timestamps
    candidates = [path.parent / "times.txt"]
    if path.parent.name == "poses":
        candidates.append(path.parent.parent / "times.txt")
    times_file = next((candidate for candidate in candidates if candidate.is_file()), None)
    if times_file is None:
        return np.arange(count) * KITTI_FRAME_PERIOD_S
    rows = _data_rows(times_file)
    times = _numbers(rows, times_file, 1, exact=False)[:, 0]
    _check_finite(times[:, None], rows, times_file)
    if len(times) != count:
        raise InputError(f"{times_file}: {len(times)} times for the {count} poses of {path.name}")
    _check_increasing(times, times_file, rows.line_numbers)
    return times


def _check_increasing(timestamps: np.ndarray, path: Path, line_numbers: list[int] | None) -> None:
    """InputError at the first timestamp not after its predecessor (the line, where the file has lines)."""
    not_after = np.flatnonzero(np.diff(timestamps) <= 0)
    if len(not_after):
        index = int(not_after[0]) + 1
        where = f"{path}:{line_numbers[index]}" if line_numbers else f"{path}: timestamp {index}"
        raise InputError(f"{where}: timestamp {timestamps[index]:.9f} does not increase "
                         f"(previous {timestamps[index - 1]:.9f})")


# ------------------------------------------------------------------------------------------------ writing


def write_trajectory(path: str | Path, trajectory: Trajectory, format: str) -> None:
    """Write ``trajectory`` to ``path`` in ``format`` (one of ``FORMATS``).

    KITTI files keep only the poses: pass the timestamps to ``read_trajectory`` (or put a times.txt beside the
    file) to get them back. Quaternions are written with a non-negative w: q and -q are the same rotation."""
    writers = {"tum": _tum_text, "kitti": _kitti_text, "euroc": _euroc_text}
    Path(path).write_text(writers[_checked_format(format)](trajectory))


def tum_line(timestamp: float, T_world_cam: np.ndarray) -> str:
    """One ``timestamp tx ty tz qx qy qz qw`` line (no newline), as ``write_trajectory`` writes it: for writers
    that add a pose at a time."""
    return _tum_rows(np.array([timestamp]), T_world_cam[None])[0]


def _tum_rows(timestamps: np.ndarray, poses: np.ndarray) -> list[str]:
    quaternions_xyzw = Rotation.from_matrix(poses[:, :3, :3]).as_quat(canonical=True)
    return _format_rows(np.column_stack([timestamps, poses[:, :3, 3], quaternions_xyzw]), " ")


def _format_rows(table: np.ndarray, separator: str) -> list[str]:
    return [separator.join(NUMBER_FORMAT % value for value in row) for row in table]


def _tum_text(trajectory: Trajectory) -> str:
    lines = _tum_rows(trajectory.timestamps, trajectory.poses)
    return "# timestamp tx ty tz qx qy qz qw\n" + "".join(line + "\n" for line in lines)


def _kitti_text(trajectory: Trajectory) -> str:
    lines = _format_rows(trajectory.poses[:, :3, :].reshape(-1, 12), " ")
    return "".join(line + "\n" for line in lines)


def _euroc_text(trajectory: Trajectory) -> str:
    quaternions_wxyz = Rotation.from_matrix(trajectory.poses[:, :3, :3]).as_quat(canonical=True)[:, [3, 0, 1, 2]]
    rows = _format_rows(np.column_stack([trajectory.positions, quaternions_wxyz]), ",")
    lines = [f"{ns},{row}" for ns, row in zip(_nanoseconds(trajectory.timestamps), rows)]
    return _EUROC_HEADER + "\n" + "".join(line + "\n" for line in lines)


def _nanoseconds(timestamps: np.ndarray) -> list[int]:
    """Integer nanoseconds; whole seconds and the fraction apart, so that 1.4e9 s does not round to 256 ns."""
    whole = np.floor(timestamps)
    fraction_ns = np.round((timestamps - whole) * NS_PER_S)
    return [int(w) * NS_PER_S + int(f) for w, f in zip(whole, fraction_ns)]
