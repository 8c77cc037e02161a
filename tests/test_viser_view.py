"""The viser page: controls driven server-side (assigning a GUI handle's value runs its callbacks, for buttons
too), the drop control against the real Player, the page served over HTTP, and (when Chromium is installed) the
page rendered by a headless browser."""

from __future__ import annotations

import shutil
import socket
import subprocess
import tempfile
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("viser")

from app.player import Player  # noqa: E402
from app.sinks.viser_view import ViserView  # noqa: E402
from app.sinks.scene import MATCH_COLOR  # noqa: E402
from vo_core.events import Event, EventKind, FrameResult, MapSnapshot  # noqa: E402
from vo_core.geometry.camera import PinholeCamera  # noqa: E402
from vo_core.trajectory import Trajectory  # noqa: E402

CAMERA = PinholeCamera(width=80, height=60, fx=70.0, fy=70.0, cx=39.5, cy=29.5)
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMIUM_TRIES = 4


class FakePlayer:
    """Records the controls the page calls."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.paused = False
        self._speed = 1.0

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
    """What the odometry sends for one tracked frame (a keyframe every fourth)."""
    keyframe = index % 4 == 0
    view.on_frame(frame(index), FrameResult(index, 0.1 * index, pose(index), True, is_keyframe=keyframe,
                                            points_2d=np.array([[10.0, 10.0], [40.0, 30.0]]),
                                            matches_2d=np.array([[20.0, 50.0, 60.0, 50.0]])))
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
    view.drop_count.value = 7
    view.drop_button.value = True
    view.play_pause.value = True
    view.restart_button.value = True
    assert player.calls == [("pause",), ("step",), ("speed", 2.5), ("drop_next", 7), ("resume",),
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


def test_drop_button_makes_the_player_skip_frames():
    """Frames dropped from the page never reach the sinks: the next frame after the click is 3 frames later."""
    player = Player([frame(i) for i in range(12)])
    view = ViserView(CAMERA, player, port=free_port())
    seen = []
    try:
        for played in player.play(on_drop=view.on_event):
            seen.append(played.index)
            if played.index == 2:
                view.drop_count.value = 3
                view.drop_button.value = True
            feed(view, played.index)
        view.refresh()
    finally:
        view.close()
    assert seen == [0, 1, 2, 6, 7, 8, 9, 10, 11]
    assert "| 9 | 9 | 2 | 3 |" in view.status.content  # processed, tracked, keyframes (0 and 8), dropped
    assert "frames_dropped (count=3" in view.event_log.content


def test_scene_layers_and_restart(fake_view):
    view, player = fake_view
    for index in range(9):
        feed(view, index)
    view.on_event(Event(EventKind.TRACKING_FAILED, 8, 0.8, {"reason": "test"}))
    view.refresh()
    nodes = {name: handle for name, (_, handle) in view._nodes.items()}
    assert {"/trajectory", "/camera", "/map/direct", "/map/features", "/keyframes/0", "/keyframes/4",
            "/keyframes/8"} <= set(nodes)
    np.testing.assert_allclose(nodes["/camera"].position, pose(8)[:3, 3])
    assert nodes["/trajectory"].points.shape == (8, 2, 3)
    assert "ERROR: frame 8 tracking_failed" in view.event_log.content
    assert view.image.image[10, 10].tolist() == [60, 230, 60]  # a tracked pixel is painted
    assert view.image.image[50, 40].tolist() == list(MATCH_COLOR)  # on the match line from (20, 50) to (60, 50)

    view.layers["direct cloud"].value = False
    assert not nodes["/map/direct"].visible and nodes["/map/features"].visible

    view.restart_button.value = True
    assert player.calls[-1] == ("request_restart",)
    assert view._nodes == {} and view.status.content == "waiting for the first frame"
    feed(view, 0)  # the new pass
    view.refresh()
    assert not view._nodes["/map/direct"][1].visible  # a switched-off layer stays off


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
    """The page's script runs, connects back over the websocket and builds the panel. The panel arrives over the
    websocket in real time, which headless Chromium's virtual time does not wait for: a few tries."""
    view, _ = fake_view
    for _ in range(CHROMIUM_TRIES):
        dom = dump_dom(view.url, budget_ms=8000)
        if "Drop frames" in dom:
            break
    assert "Drop frames" in dom and "Frames to drop" in dom and "FDMO" in dom


def dump_dom(url: str, budget_ms: int) -> str:
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--no-first-run", f"--user-data-dir={profile}",
             f"--virtual-time-budget={budget_ms}", "--dump-dom", url],
            capture_output=True, text=True, timeout=120,
        ).stdout
