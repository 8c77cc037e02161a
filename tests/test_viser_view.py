"""The viser page: controls driven server-side (assigning a GUI handle's value runs its callbacks, for buttons
too), the drop and jump-back controls against the real Player, Restart through the pipeline (a new recording),
the page served over HTTP, and (when Chromium is installed) the page in a headless browser: its buttons clicked,
its scene read back."""

from __future__ import annotations

import socket
import threading
import time
import warnings
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest
from fake_sequence import FakeSequence

pytest.importorskip("viser")

from chromium_page import CHROMIUM, ChromiumPage  # noqa: E402

from app.pipeline import run_sequence  # noqa: E402
from app.player import Player  # noqa: E402
from app.sinks.scene import MATCH_INLIER_COLOR, MATCH_OUTLIER_COLOR  # noqa: E402
from app.sinks.viser_view import ViserView  # noqa: E402
from vo_core.config import load_config  # noqa: E402
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot  # noqa: E402
from vo_core.geometry.camera import PinholeCamera  # noqa: E402
from vo_core.synthetic import make_sequence  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402

CAMERA = PinholeCamera(width=80, height=60, fx=70.0, fy=70.0, cx=39.5, cy=29.5)


class FakePlayer:
    """Records the controls the page calls."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.paused = False
        self.finished = False
        self._speed = 1.0
        self.clock = 0.0  # playing time, set by the test

    @property
    def speed(self) -> float:
        return self._speed

    @speed.setter
    def speed(self, value: float) -> None:
        self._speed = value
        self.calls.append(("speed", value))

    def pause(self) -> None:
        self.paused = True
        self.calls.append(("pause",))

    def resume(self) -> None:
        self.paused = False
        self.calls.append(("resume",))

    def step(self) -> None:
        self.calls.append(("step",))

    def drop_next(self, count: int) -> None:
        self.calls.append(("drop_next", count))

    def jump_back(self, count: int) -> None:
        self.calls.append(("jump_back", count))

    def playing_time(self) -> float:
        return self.clock

    def request_restart(self) -> None:
        self.calls.append(("request_restart",))

    def stop(self) -> None:
        self.calls.append(("stop",))


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def frame(index: int) -> SimpleNamespace:
    return SimpleNamespace(index=index, timestamp=0.1 * index, image=np.full((60, 80), 10 * index % 256, np.uint8))


def pose(index: int) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.1 * index, 0.0, 0.02 * index]
    return T


def feed(view: ViserView, index: int) -> None:
    """What the odometry sends for one tracked frame (a keyframe every fourth): a match kept by the pose (a line
    along row 50) and one it rejected (along row 55)."""
    keyframe = index % 4 == 0
    view.on_frame(frame(index), FrameResult(index, 0.1 * index, pose(index), True, is_keyframe=keyframe,
                                            points_2d=np.array([[10.0, 10.0], [40.0, 30.0]]),
                                            matches_2d=np.array([[20.0, 50.0, 60.0, 50.0], [20.0, 55.0, 60.0, 55.0]]),
                                            matches_inlier=np.array([True, False]), divergence_ratio=0.9,
                                            divergence_threshold=1.1))
    if keyframe:
        rng = np.random.default_rng(index)
        view.on_map(MapSnapshot(rng.normal(size=(40, 3)), rng.uniform(0.2, 2.0, 40), rng.normal(size=(10, 3)),
                                {k: pose(k) for k in range(0, index + 1, 4)}))


@pytest.fixture
def fake_view():
    player = FakePlayer()
    view = ViserView(CAMERA, player, port=free_port(), refresh_hz=50.0)
    yield view, player
    view.close()


def test_controls_call_the_player(fake_view):
    view, player = fake_view
    view.play_pause.value = True  # a click
    view.step_button.value = True
    view.speed.value = 2.5
    view.frame_count.value = 7
    view.drop_button.value = True
    view.frame_count.value = 4
    view.jump_button.value = True
    view.play_pause.value = True
    view.restart_button.value = True
    assert player.calls == [("pause",), ("step",), ("speed", 2.5), ("drop_next", 7), ("jump_back", 4), ("resume",),
                            ("request_restart",)]


def test_play_button_shows_the_player_state(fake_view):
    view, player = fake_view
    view.play_pause.value = True
    assert (player.paused, view.play_pause.label) == (True, "Play")
    view.play_pause.value = True
    assert (player.paused, view.play_pause.label) == (False, "Pause")


def test_status_follows_the_player_without_a_new_frame(fake_view):
    view, player = fake_view
    feed(view, 0)
    view.refresh()
    assert view.status.content.startswith("**tracking** at frame 0")
    player.paused = True
    view.refresh()
    assert view.status.content.startswith("**tracking, paused**")
    player.finished = True
    view.refresh()
    assert view.status.content.startswith("**tracking, sequence finished**")
    # The button no longer says "Pause" once nothing plays: a Play that cannot be pressed (Restart plays again).
    assert (view.play_pause.label, view.play_pause.disabled) == ("Play", True)


def test_status_shows_the_terminals_frame_rate_and_the_divergence_test(fake_view):
    view, player = fake_view
    player.clock = 10.0
    view.restart()  # a pass starts at playing time 10 s
    for index in range(6):
        feed(view, index)
    player.clock = 12.0  # 6 frames in 2 s of playing time (pauses are not in this clock)
    view.refresh()
    assert "3.0 fps" in view.status.content
    assert "divergence ratio 0.900, below the threshold 1.100" in view.status.content


def play_with_clicks(clicks: dict[int, tuple[str, int]], frames: int = 14) -> tuple[list[int], ViserView]:
    """Frames the odometry receives from a real Player while the page's buttons are clicked as frames arrive:
    ``clicks`` maps the n-th frame received to (button, N)."""
    player = Player(FakeSequence(frame(i) for i in range(frames)))
    view = ViserView(CAMERA, player, port=free_port())
    seen = []
    try:
        for played in player.play(on_event=view.on_event):
            seen.append(played.index)
            if len(seen) in clicks:
                button, count = clicks[len(seen)]
                view.frame_count.value = count
                getattr(view, button).value = True
            feed(view, played.index)
        view.refresh()
    finally:
        view.close()
    return seen, view


def test_drop_button_makes_the_player_skip_frames():
    """Frames dropped from the page never reach the sinks: the next frame after the click is 3 frames later."""
    seen, view = play_with_clicks({3: ("drop_button", 3)}, frames=12)
    assert seen == [0, 1, 2, 6, 7, 8, 9, 10, 11]
    # processed, tracked, keyframes (0 and 8), dropped, jumps
    assert "| 9 | 9 | 2 | 3 | 0 |" in view.status.content
    assert "frames_dropped (count=3" in view.event_log.content


def test_jump_back_button_makes_the_player_replay_frames():
    seen, view = play_with_clicks({6: ("jump_button", 4)}, frames=9)
    assert seen == [0, 1, 2, 3, 4, 5, 1, 2, 3, 4, 5, 6, 7, 8]
    assert "| 14 | 14 |" in view.status.content and "| 0 | 1 |" in view.status.content
    assert "frames_jumped (from_frame=5, to_frame=1, direction=backward, frames=5" in view.event_log.content


def test_scene_layers_and_restart(fake_view):
    view, player = fake_view
    for index in range(9):
        feed(view, index)
    view.on_event(Event(EventKind.TRACKING_FAILED, 8, 0.8, {"reason": "test"}))
    view.refresh()
    feed(view, 9)  # the failure is marked at the next frame's pose
    view.refresh()
    nodes = {name: handle for name, (_, handle) in view._nodes.items()}
    assert {"/trajectory", "/camera", "/map/direct", "/map/features", "/keyframes/0", "/keyframes/4",
            "/keyframes/8", "/events/tracking_failed"} <= set(nodes)
    np.testing.assert_allclose(nodes["/camera"].position, pose(9)[:3, 3])
    np.testing.assert_allclose(nodes["/events/tracking_failed"].points, [pose(9)[:3, 3]], atol=1e-6)  # float32
    assert nodes["/trajectory"].points.shape == (9, 2, 3)
    assert "ERROR: frame 8 tracking_failed" in view.event_log.content
    assert view.image.image[10, 10].tolist() == [60, 230, 60]  # a tracked pixel is painted
    assert view.image.image[50, 40].tolist() == list(MATCH_INLIER_COLOR)  # on the inlier from (20, 50) to (60, 50)
    assert view.image.image[55, 40].tolist() == list(MATCH_OUTLIER_COLOR)  # on the outlier along row 55
    ratio = view.divergence_plot.data[1]
    np.testing.assert_allclose(ratio, 0.9)
    failures = view.divergence_plot.data[3]  # the "divergence" series: tracking failures among them
    assert np.flatnonzero(np.isfinite(failures)).tolist() == [9]

    view.layers["direct cloud"].value = False
    assert not nodes["/map/direct"].visible and nodes["/map/features"].visible

    view.restart()  # what the pipeline does when a new pass starts
    view.refresh()
    assert view._nodes == {} and view.status.content == "waiting for the first frame"
    feed(view, 0)  # the new pass
    view.refresh()
    assert not view._nodes["/map/direct"][1].visible  # a switched-off layer stays off


def test_far_points_reach_the_page_as_float32_without_overflow(fake_view):
    """Issue 47: viser's default float16 turned far feature points into inf, with a RuntimeWarning."""
    view, _ = fake_view
    far = np.array([[1.0e6, 2.0, 3.0], [100.123, -7.0e4, 0.5]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow in a cast fails the test
        view.on_frame(frame(0), FrameResult(0, 0.0, pose(0), True, is_keyframe=True))
        view.on_map(MapSnapshot(far, np.ones(2), far, {0: pose(0)}))
        view.refresh()
    for name in ("/map/direct", "/map/features"):
        points = view._nodes[name][1].points
        assert points.dtype == np.float32
        np.testing.assert_allclose(points, far, rtol=1e-6)


def wait_until(condition, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


class PassRecorder:
    """A sink that lists the frames the odometry processed, a list per pass (it is told of each restart)."""

    def __init__(self) -> None:
        self.passes: list[list[int]] = [[]]

    def restart(self) -> None:
        self.passes.append([])

    def on_frame(self, frame, result) -> None:
        self.passes[-1].append(result.frame_index)

    def on_event(self, event) -> None:
        pass

    def on_map(self, snapshot) -> None:
        pass

    def close(self) -> None:
        pass


def click_restart_on_the_server(view: ViserView, restarted) -> None:
    view.restart_button.value = True


def click_restart_in_chromium(view: ViserView, restarted) -> None:
    """A real click on the page's button; the page stays open until the run has restarted (closing it at once could
    drop the click on its way)."""
    page = ChromiumPage(view.url)
    try:
        page.wait_for("document.body.innerText.includes('sequence finished')")
        page.click("Restart")
        wait_until(restarted)
    finally:
        page.close()


@pytest.mark.parametrize("click_restart", [
    click_restart_on_the_server,
    pytest.param(click_restart_in_chromium, marks=pytest.mark.skipif(CHROMIUM is None,
                                                                     reason="chromium is not installed")),
])
def test_restart_from_the_page_starts_a_new_rerun_recording(tmp_path, click_restart):
    """The whole pipeline with the page and a recording: after Restart (assigned on the server, or clicked in the
    page in headless Chromium) the file holds a new recording (a new id) with the second pass alone, and the page
    counts the second pass alone."""
    from app.sinks.rerun_sink import RerunSink
    import rerun as rr

    sequence = make_sequence("smooth", 6, seed=0, width=160, height=120)
    player = Player(sequence)
    recording = RerunSink(tmp_path / "recording.rrd", sequence.camera, recording_name="synthetic")
    view = ViserView(sequence.camera, player, port=free_port())
    processed = PassRecorder()
    run = threading.Thread(target=run_sequence, daemon=True, args=(sequence, load_config(overrides=["method=klt"]),
                                                                   tmp_path / "out", [recording, view, processed]),
                           kwargs={"player": player, "keep_alive": True})
    run.start()
    wait_until(lambda: player.finished)
    first_id = recording.recording.get_recording_id()
    click_restart(view, lambda: len(processed.passes) == 2)
    wait_until(lambda: len(processed.passes) == 2 and len(processed.passes[1]) == len(sequence) and player.finished)
    view.refresh()
    player.stop()
    run.join(timeout=30)
    assert not run.is_alive()
    entries = rr.chunk.RrdReader(tmp_path / "recording.rrd").recordings()
    assert [entry.recording_id for entry in entries] == [recording.recording.get_recording_id()]
    assert entries[0].recording_id != first_id
    images = [chunk for chunk in rr.chunk.RrdReader(tmp_path / "recording.rrd").stream().to_chunks()
              if chunk.entity_path == "/world/camera/image"]
    blobs = sum(1 for chunk in images for blob in chunk.to_record_batch().to_pydict().get("EncodedImage:blob", [])
                if blob is not None)
    assert blobs == len(sequence)  # one image per frame, not the two passes on one timeline
    assert "| 6 |" in view.status.content.splitlines()[-1]


def test_ground_truth_is_drawn_aligned():
    scaled = np.array([pose(i) for i in range(9)])
    scaled[:, :3, 3] = 3.0 * scaled[:, :3, 3] + [5.0, -1.0, 2.0]  # the path at another scale and place
    view = ViserView(CAMERA, FakePlayer(), Trajectory(0.1 * np.arange(9), scaled), port=free_port())
    try:
        for index in range(9):
            feed(view, index)
        view.refresh()
        segments = view._nodes["/ground_truth"][1].points
    finally:
        view.close()
    np.testing.assert_allclose(segments[:, 0], [pose(i)[:3, 3] for i in range(8)], atol=1e-5)


def test_page_is_served_over_http(fake_view):
    view, _ = fake_view
    with urllib.request.urlopen(view.url, timeout=10) as response:
        page = response.read().decode()
    assert response.status == 200 and "<html" in page.lower()


def accepts_connections(host: str, port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(5.0)
        return probe.connect_ex((host, port)) == 0


def test_the_page_listens_on_the_loopback_address_only_unless_asked():
    """Every 127.x.y.z reaches this machine: a server bound to 127.0.0.1 alone refuses 127.0.0.2."""
    view = ViserView(CAMERA, FakePlayer(), port=free_port())
    try:
        assert view.url.startswith("http://127.0.0.1:")
        assert accepts_connections("127.0.0.1", view.port) and not accepts_connections("127.0.0.2", view.port)
    finally:
        view.close()
    elsewhere = ViserView(CAMERA, FakePlayer(), host="127.0.0.2", port=free_port())
    try:
        assert accepts_connections("127.0.0.2", elsewhere.port) and not accepts_connections("127.0.0.1", elsewhere.port)
    finally:
        elsewhere.close()


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_headless_chromium_renders_the_controls(fake_view):
    """The page's script runs, connects back over the websocket and builds the panel."""
    view, _ = fake_view
    page = ChromiumPage(view.url)
    try:
        text = page.wait_for("document.body.innerText.includes('Jump back N frames') && document.body.innerText")
    finally:
        page.close()
    assert "Drop N frames" in text and "N frames" in text and "FDMO" in text and "divergence" in text


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_drop_and_jump_back_clicked_in_the_page_change_what_the_odometry_receives():
    """Playback waits for the browser; then a click on "Drop N frames" and one on "Jump back N frames" (N = 3): the
    frames the odometry receives skip 3 frames ahead and go 3 frames back. The scene then holds both clouds."""
    # 10 frames a second, for 30 s at most: time to click, even on a busy machine (the run ends once both clicks
    # have taken effect).
    player = Player(FakeSequence(frame(i) for i in range(300)))
    player.speed = 1.0
    view = ViserView(CAMERA, player, port=free_port(), wait_for_browser=True)
    view.frame_count.value = 3
    seen: list[int] = []

    def track() -> None:
        for played in player.play(on_event=view.on_event):
            seen.append(played.index)
            feed(view, played.index)

    odometry = threading.Thread(target=track, daemon=True)
    odometry.start()
    page = None
    try:
        time.sleep(1.0)
        assert seen == []  # held until a browser opens the page
        page = ChromiumPage(view.url)
        page.wait_for(r"+(document.body.innerText.match(/at frame (\d+)/) || [0, 0])[1] >= 5")
        page.click("Drop N frames")
        page.wait_for("document.body.innerText.includes('frames_dropped')")
        page.click("Jump back N frames")
        page.wait_for("document.body.innerText.includes('frames_jumped')")
        player.stop()
        odometry.join(timeout=60)
        clouds = page.wait_for("['/map/direct', '/map/features'].every(name => name in "
                               "window.__viserSceneTree.getState())")
    finally:
        player.stop()
        if page is not None:
            page.close()
        view.close()
    steps = np.diff(seen).tolist()
    assert seen[0] == 0 and steps.count(4) == 1 and steps.count(-3) == 1  # a drop of 3, a jump 3 back
    assert set(steps) == {1, 4, -3} and clouds
