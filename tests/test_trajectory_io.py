"""Trajectory files: TUM, KITTI and EuRoC CSV round trips, format detection, and one-line errors for bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vo_core.errors import InputError
from vo_core.geometry.lie import se3_exp
from vo_core.trajectory import Trajectory, detect_format, read_trajectory, tum_line, write_trajectory

# Written with %.9f: positions and rotation entries come back to ~1e-9.
FILE_PRECISION = 2e-9


def random_trajectory(count: int = 25, start_s: float = 1403715274.302142976) -> Trajectory:
    """Poses with large rotations, timestamps with EuRoC-sized epoch seconds and irregular spacing."""
    rng = np.random.default_rng(7)
    twists = rng.normal(scale=[2.0, 2.0, 2.0, 1.5, 1.5, 1.5], size=(count, 6))
    timestamps = start_s + np.cumsum(rng.uniform(0.01, 0.1, size=count))
    return Trajectory(timestamps, np.array([se3_exp(xi) for xi in twists]))


def assert_same(read: Trajectory, written: Trajectory, timestamp_tolerance: float = 1e-9) -> None:
    assert len(read) == len(written)
    np.testing.assert_allclose(read.timestamps, written.timestamps, rtol=0, atol=timestamp_tolerance)
    np.testing.assert_allclose(read.poses, written.poses, rtol=0, atol=FILE_PRECISION)
    rotations = read.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)


# --------------------------------------------------------------------------------------------- round trips


def test_tum_round_trip_keeps_nanosecond_timestamps(tmp_path):
    trajectory = random_trajectory()
    write_trajectory(tmp_path / "est.tum", trajectory, "tum")
    # Epoch seconds need 19 significant digits for nanoseconds; %.9f keeps them (float64 holds ~0.2 us).
    assert_same(read_trajectory(tmp_path / "est.tum"), trajectory, timestamp_tolerance=3e-7)
    first_line = (tmp_path / "est.tum").read_text().splitlines()[1]
    assert first_line == tum_line(trajectory.timestamps[0], trajectory.poses[0])  # for writers of a pose at a time
    first_stamp = first_line.split()[0]
    assert first_stamp.startswith("1403715274.") and len(first_stamp.split(".")[1]) == 9


def test_euroc_round_trip_converts_nanoseconds(tmp_path):
    trajectory = random_trajectory()
    write_trajectory(tmp_path / "data.csv", trajectory, "euroc")
    header, first_line = (tmp_path / "data.csv").read_text().splitlines()[:2]
    assert header.startswith("#timestamp [ns]")
    assert abs(int(first_line.split(",")[0]) - trajectory.timestamps[0] * 1e9) < 512  # integer nanoseconds
    assert_same(read_trajectory(tmp_path / "data.csv"), trajectory, timestamp_tolerance=3e-7)


def test_kitti_round_trip_with_timestamps_given_beside_or_by_index(tmp_path):
    trajectory = random_trajectory(start_s=0.0)
    path = tmp_path / "poses.txt"
    write_trajectory(path, trajectory, "kitti")
    assert len(path.read_text().splitlines()[0].split()) == 12
    assert_same(read_trajectory(path, format="kitti", timestamps=trajectory.timestamps), trajectory)
    # Without timestamps: KITTI's 10 Hz frame index...
    by_index = read_trajectory(path)
    np.testing.assert_allclose(by_index.timestamps, np.arange(len(trajectory)) * 0.1)
    # ...unless a times.txt lies beside the poses, as in KITTI's sequence folders.
    np.savetxt(tmp_path / "times.txt", trajectory.timestamps, fmt="%.9e")
    assert_same(read_trajectory(path), trajectory)



def test_kitti_poses_folder_takes_the_times_of_its_sequence_folder(tmp_path):
    """The layout the KITTI loader reads: SEQUENCE/times.txt and SEQUENCE/poses/00.txt."""
    trajectory = random_trajectory(start_s=0.0)
    (tmp_path / "poses").mkdir()
    write_trajectory(tmp_path / "poses" / "00.txt", trajectory, "kitti")
    np.savetxt(tmp_path / "times.txt", trajectory.timestamps, fmt="%.9e")
    assert_same(read_trajectory(tmp_path / "poses" / "00.txt"), trajectory)


def test_rotations_written_with_few_decimals_are_made_exact(tmp_path):
    trajectory = random_trajectory(count=5, start_s=0.0)
    rounded = "\n".join(" ".join(f"{v:.4f}" for v in pose[:3].ravel()) for pose in trajectory.poses)
    (tmp_path / "poses.txt").write_text(rounded + "\n")
    rotations = read_trajectory(tmp_path / "poses.txt").poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (5, 3, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(rotations, trajectory.poses[:, :3, :3], atol=2e-4)


def test_unnormalized_quaternions_and_comma_separated_tum(tmp_path):
    # qw = 2 (not normalized): the identity rotation; comma separators and comments are accepted.
    (tmp_path / "gt.txt").write_text("# comment\n0.5, 1, 2, 3, 0, 0, 0, 2\n\n0.6,1,2,3,0,0,0,-3\n")
    trajectory = read_trajectory(tmp_path / "gt.txt")
    np.testing.assert_allclose(trajectory.timestamps, [0.5, 0.6])
    np.testing.assert_allclose(trajectory.poses[:, :3, :3], np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-15)
    np.testing.assert_allclose(trajectory.positions, [[1, 2, 3], [1, 2, 3]])


def test_euroc_state_file_extra_columns_and_quaternion_order(tmp_path):
    header = "#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z [],v_RS_R_x"
    # 90 degrees about z: (qw, qx, qy, qz) = (cos 45, 0, 0, sin 45).
    line = "1403715273262142976,4.688,-1.786,0.783,0.7071067811865476,0,0,0.7071067811865476,0.1"
    (tmp_path / "data.csv").write_text(f"{header}\n{line}\n")
    trajectory = read_trajectory(tmp_path / "data.csv")
    assert trajectory.timestamps[0] == pytest.approx(1403715273.262142976, abs=1e-6)
    np.testing.assert_allclose(trajectory.poses[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_tum_monovo_lines_without_a_pose_are_skipped(tmp_path):
    lines = ["0.0 1 2 3 0 0 0 1", "0.1 NaN NaN NaN NaN NaN NaN NaN", "0.2 4 5 6 0 0 0 1"]
    (tmp_path / "groundtruthSync.txt").write_text("\n".join(lines) + "\n")
    np.testing.assert_allclose(read_trajectory(tmp_path / "groundtruthSync.txt").timestamps, [0.0, 0.2])


@pytest.mark.parametrize(
    "name, content, expected",
    [
        ("a.tum", "0 0 0 0 0 0 0 1\n", "tum"),
        ("a.kitti", "1 0 0 0 0 1 0 0 0 0 1 0\n", "kitti"),
        ("a.csv", "1403715273262142976,0,0,0,1,0,0,0\n", "euroc"),
        ("groundtruth.txt", "# timestamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n", "tum"),
        ("00.txt", "1 0 0 0 0 1 0 0 0 0 1 0\n", "kitti"),
        ("gt.txt", "#timestamp [ns], x, y, z, qw, qx, qy, qz\n1000,0,0,0,1,0,0,0\n", "euroc"),
        ("state.txt", "1403715273262142976 0 0 0 1 0 0 0 0 0 0\n", "euroc"),
    ],
)
def test_format_is_detected_from_extension_or_content(tmp_path, name, content, expected):
    (tmp_path / name).write_text(content)
    assert detect_format(tmp_path / name) == expected


# -------------------------------------------------------------------------------------------- bad files


@pytest.mark.parametrize(
    "content, message",
    [
        ("0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n", "gt.tum:2: expected 8 numbers, found 7"),
        ("0.0 0 0 0 0 0 0 1\n0.1 0 0 x 0 0 0 1\n", "gt.tum:2: not a number"),
        ("# header\n0.0 0 0 0 0 0 0 1\n0.1 0 inf 0 0 0 0 1\n", "gt.tum:3: non-finite value"),
        ("0.0 0 0 0 0 0 0 1\n0.2 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 1\n", "gt.tum:3: timestamp 0.100000000 does not"),
        ("0.0 0 0 0 0 0 0 1\n0.0 0 0 0 0 0 0 1\n", "gt.tum:2: timestamp 0.000000000 does not increase"),
        ("0.0 0 0 0 0 0 0 0\n", "gt.tum:1: zero quaternion"),
        ("# only a comment\n", "gt.tum: no data lines"),
    ],
)
def test_malformed_tum_files_name_the_file_and_line(tmp_path, content, message):
    (tmp_path / "gt.tum").write_text(content)
    with pytest.raises(InputError, match=message.replace(".", r"\.")) as error:
        read_trajectory(tmp_path / "gt.tum")
    assert str(tmp_path / "gt.tum") in str(error.value) and "\n" not in str(error.value)


def test_malformed_kitti_files_name_the_file_and_line(tmp_path):
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"poses\.txt:2: the 3x3 block is not a rotation"):
        read_trajectory(path, format="kitti")
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(InputError, match=r"times\.txt: 2 times for the 1 poses of poses\.txt"):
        read_trajectory(path)


@pytest.mark.parametrize(
    "path, format, message",
    [
        (Path("missing.tum"), None, "missing.tum: trajectory file not found"),
        (Path(__file__), "g2o", "unknown trajectory format 'g2o'"),
    ],
)
def test_missing_file_and_unknown_format(path, format, message):
    with pytest.raises(InputError, match=message):
        read_trajectory(path, format=format)


def test_unrecognizable_content_asks_for_the_format(tmp_path):
    (tmp_path / "poses.txt").write_text("1 2 3 4 5\n")
    with pytest.raises(InputError, match=r"poses\.txt: cannot tell the trajectory format \(5 numbers a line;"):
        read_trajectory(tmp_path / "poses.txt")
