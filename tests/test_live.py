"""A live camera (``fdmo run camera:N --camera FILE``), with OpenCV's VideoCapture replaced by a camera that delivers
a rendered sequence at its own pace: the run takes the newest frame each time, says how many it missed, and ends
with valid files when the camera stops; options a live camera cannot honour are refused in one line."""

from __future__ import annotations

import json
import time

import cv2
import pytest
from test_cli import run_cli

from vo_core.synthetic import make_sequence
from vo_core.trajectory import read_trajectory

SEQUENCE = make_sequence("smooth", 60, seed=0, width=320, height=240)
DELIVERY_INTERVAL_S = 1 / 30.0


class RenderedCamera:
    """What cv2.VideoCapture(device) gives: the sequence's images as BGR, one per interval, then nothing (the
    camera was unplugged)."""

    def __init__(self, device):
        self.device = device
        self.images = iter(frame.image for frame in SEQUENCE)

    def isOpened(self) -> bool:
        return self.device == 0

    def read(self):
        time.sleep(DELIVERY_INTERVAL_S)
        image = next(self.images, None)
        return (False, None) if image is None else (True, cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))

    def release(self) -> None:
        pass


@pytest.fixture
def calibration(tmp_path, monkeypatch):
    monkeypatch.setattr(cv2, "VideoCapture", RenderedCamera)
    camera = SEQUENCE.camera
    path = tmp_path / "camera.yaml"
    path.write_text(f"model: pinhole\nintrinsics: [{camera.fx}, {camera.fy}, {camera.cx}, {camera.cy}]\n"
                    f"resolution: [{camera.width}, {camera.height}]\n")
    return path


def test_a_live_camera_is_tracked_newest_frame_first_until_it_stops(calibration, tmp_path, capsys):
    out = tmp_path / "out"
    code, stdout, stderr = run_cli(capsys, "run", "camera:0", "--camera", calibration, "--out", out, "--no-rrd")
    assert code == 0, stderr
    assert "live from camera:0 (320x240 rectified)" in stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "completed" and metrics["frames"] == len(SEQUENCE)
    # Every frame the camera delivered was processed or reported as missed, never both.
    assert metrics["processed_frames"] + metrics["late_frames"] == len(SEQUENCE)
    assert metrics["tracked_frames"] > 0
    assert len(read_trajectory(out / "trajectory.tum")) == metrics["posed_frames"]
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    late = [e for e in events if e["kind"] == "frames_dropped"]
    assert sum(e["details"]["count"] for e in late) == metrics["late_frames"]
    assert {e["details"]["source"] for e in late} <= {"realtime"}


@pytest.mark.parametrize("argv, message", [
    (["camera:0"], "camera:0: a live camera needs its calibration (--camera FILE)"),
    (["camera:0", "--camera", "{calibration}", "--drop", "5:3"], "camera:0: --drop cannot be used with a live camera"),
    (["camera:0", "--camera", "{calibration}", "--start", "2", "--viser"],
     "camera:0: --start, --viser cannot be used with a live camera"),
    (["camera:3", "--camera", "{calibration}"], "camera:3: OpenCV cannot open this camera"),
    (["camera:front", "--camera", "{calibration}"], "camera:front: expected camera:N"),
])
def test_what_a_live_camera_cannot_do_is_refused_in_one_line(calibration, tmp_path, capsys, argv, message):
    argv = [str(a).format(calibration=calibration) for a in argv]
    code, _, stderr = run_cli(capsys, "run", *argv, "--out", tmp_path / "out", "--no-rrd", "--quiet")
    assert code == 2
    assert len(stderr.strip().splitlines()) == 1 and message in stderr
