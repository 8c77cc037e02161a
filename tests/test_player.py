"""The Player: frames in order, scripted and live drops and jumps, pause/step, pacing, restart and stop."""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass

import pytest
from fake_sequence import FakeSequence

from app.player import Player
from vo_core.events import EventKind

RATE_HZ = 20.0
WAIT_S = 5.0  # generous bound for a frame that must arrive; never reached when the player works


@dataclass
class FakeFrame:
    index: int
    timestamp: float


def frames(count: int, first_index: int = 0) -> FakeSequence:
    return FakeSequence(FakeFrame(i, i / RATE_HZ) for i in range(first_index, first_index + count))


def play_all(player: Player) -> tuple[list[int], list]:
    events = []
    seen = [frame.index for frame in player.play(on_event=events.append)]
    return seen, events


class Consumer:
    """Iterates a player on a thread, as the tracking thread does, and hands each frame over a queue."""

    def __init__(self, player: Player):
        self.player = player
        self.received: queue.Queue = queue.Queue()
        self.events: list = []
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        for frame in self.player.play(on_event=self.events.append):
            self.received.put(frame.index)
        self.received.put(None)

    def next(self, timeout: float = WAIT_S):
        return self.received.get(timeout=timeout)

    def nothing_within(self, seconds: float) -> bool:
        try:
            self.received.get(timeout=seconds)
        except queue.Empty:
            return True
        return False


def test_all_frames_in_order_without_drops():
    player = Player(frames(10))
    seen, events = play_all(player)
    assert seen == list(range(10))
    assert events == []
    assert player.finished


def test_scripted_drops_hide_frames_and_say_so():
    # Indices are the original frame numbers: a sequence cut to start at frame 100.
    player = Player(frames(20, first_index=100), drops=[(103, 4), (110, 1)])
    seen, events = play_all(player)
    assert seen == [100, 101, 102, 107, 108, 109] + list(range(111, 120))
    assert [e.kind for e in events] == [EventKind.FRAMES_DROPPED] * 2
    first = events[0]
    assert (first.frame_index, first.timestamp) == (103, 103 / RATE_HZ)
    assert first.details == {"count": 4, "requested": 4, "first_frame": 103, "last_frame": 106, "source": "script"}
    assert events[1].details["count"] == 1 and events[1].details["last_frame"] == 110


def test_a_drop_past_the_end_reports_the_frames_it_could_drop():
    seen, events = play_all(Player(frames(6), drops=[(4, 10)]))
    assert seen == [0, 1, 2, 3]
    assert events[0].details["count"] == 2 and events[0].details["requested"] == 10


def test_live_drop_acts_at_the_next_frame_like_a_scripted_one():
    player = Player(frames(12))
    seen, events = [], []
    for frame in player.play(on_event=events.append):
        seen.append(frame.index)
        if frame.index == 2:
            player.drop_next(3)  # a click on the page while frame 2 is being tracked
    assert seen == [0, 1, 2] + list(range(6, 12))
    assert events[0].details == {"count": 3, "requested": 3, "first_frame": 3, "last_frame": 5, "source": "live"}


def test_pause_holds_frames_step_releases_exactly_one_resume_continues():
    player = Player(frames(8))
    player.pause()
    consumer = Consumer(player)
    assert consumer.nothing_within(0.3)
    player.step()
    assert consumer.next() == 0
    assert consumer.nothing_within(0.3)
    player.step()
    player.step()
    assert [consumer.next(), consumer.next()] == [1, 2]
    assert consumer.nothing_within(0.2) and player.paused
    player.resume()
    assert [consumer.next() for _ in range(5)] == [3, 4, 5, 6, 7]
    assert consumer.next() is None


def test_a_drop_while_paused_applies_when_playback_continues():
    player = Player(frames(8))
    player.pause()
    consumer = Consumer(player)
    player.drop_next(2)
    player.step()
    assert consumer.next() == 2
    assert consumer.events[0].details["first_frame"] == 0


def test_speed_paces_frames_at_the_dataset_rate():
    player = Player(frames(6))  # 0.25 s of dataset time at 20 Hz
    player.speed = 2.0
    started = time.monotonic()
    seen, _ = play_all(player)
    assert seen == list(range(6))
    assert time.monotonic() - started >= 0.25 / 2.0 - 0.01


def test_realtime_hands_out_the_newest_frame_and_drops_the_frames_missed_meanwhile():
    """A tracker 3 frame intervals slow sees about one frame in 3; every other frame is dropped as late, none is
    read, and the camera's clock never waits for the tracker (the run takes the sequence's own time)."""
    sequence = frames(30)  # 1.5 s at 20 Hz
    player = Player(sequence, realtime=True)
    seen, events = [], []
    started = time.monotonic()
    for frame in player.play(on_event=events.append):
        seen.append(frame.index)
        time.sleep(3 / RATE_HZ)
    elapsed = time.monotonic() - started
    late = [event for event in events if event.kind is EventKind.FRAMES_DROPPED]
    assert all(event.details["source"] == "realtime" for event in late)
    assert len(seen) + sum(event.details["count"] for event in late) == 30
    assert 30 / 4 <= len(seen) <= 30 / 2.5 and seen == sorted(seen) and seen[0] == 0
    assert sequence.reads == seen  # frames dropped are never read
    # The camera's own time (1.5 s) against a player that waited for the tracker (30 frames x 0.15 s = 4.5 s): the
    # bound halfway between tells them apart on a loaded machine too (1.5 s plus a frame's tracking failed at 1.71 s).
    camera_s, waiting_s = 30 / RATE_HZ, 30 * 3 / RATE_HZ
    assert elapsed < (camera_s + waiting_s) / 2


def test_realtime_with_a_fast_tracker_drops_nothing_and_keeps_the_frame_rate():
    started = time.monotonic()
    seen, events = play_all(Player(frames(10), realtime=True))  # 0.45 s between the first and the last frame
    assert seen == list(range(10)) and events == []
    assert time.monotonic() - started >= 9 / RATE_HZ - 0.01


def test_speed_must_not_be_negative():
    with pytest.raises(ValueError, match="speed"):
        Player(frames(1)).speed = -1.0


def test_restart_ends_the_pass_and_the_next_pass_starts_over_with_the_script():
    player = Player(frames(10), drops=[(1, 1)])
    seen = []
    for frame in player.play():
        seen.append(frame.index)
        if frame.index == 4:
            player.request_restart()
    assert seen == [0, 2, 3, 4]
    assert not player.finished and player.wait_for_restart()
    seen, events = play_all(player)
    assert seen == [0] + list(range(2, 10))
    assert len(events) == 1


def test_stop_ends_playback_and_wait_for_restart_returns_false():
    player = Player(frames(100))
    player.pause()
    consumer = Consumer(player)
    player.step()
    assert consumer.next() == 0
    player.stop()
    assert consumer.next() is None  # the pass ended: no frame after the stop
    assert not player.finished
    assert player.wait_for_restart() is False


def test_wait_for_restart_wakes_on_a_request_from_another_thread():
    player = Player(frames(3))
    play_all(player)
    threading.Timer(0.1, player.request_restart).start()
    assert player.wait_for_restart() is True


@pytest.mark.parametrize("drop", [(-1, 2), (3, 0)])
def test_invalid_scripted_drops_are_refused(drop):
    with pytest.raises(ValueError, match="drop"):
        Player(frames(5), drops=[drop])


def test_interrupt_ends_the_pass_even_while_paused_and_says_so():
    player = Player(frames(100))
    player.pause()
    consumer = Consumer(player)
    player.step()
    assert consumer.next() == 0
    player.interrupt()
    assert consumer.next() is None  # the wait polls: no notification needed
    assert player.interrupted and player.stopped and not player.finished
    assert player.wait_for_restart() is False


def test_interrupt_takes_no_lock():
    """A signal handler runs between two bytecodes of the main thread, maybe while it holds the player's lock."""
    player = Player(frames(3))
    holding, release = threading.Event(), threading.Event()

    def hold_the_lock():
        with player._condition:
            holding.set()
            release.wait(WAIT_S)

    threading.Thread(target=hold_the_lock, daemon=True).start()
    assert holding.wait(WAIT_S)
    interrupting = threading.Thread(target=player.interrupt, daemon=True)
    interrupting.start()
    interrupting.join(timeout=1.0)
    release.set()
    assert not interrupting.is_alive() and player.interrupted


# ------------------------------------------------------------------------------------ jumps


def test_a_backward_jump_replays_the_frames_since_its_target_once():
    seen, events = play_all(Player(frames(12), jumps=[(7, 3)]))
    assert seen == list(range(8)) + list(range(3, 12))  # frame 7 is reached again and does not jump again
    assert [e.kind for e in events] == [EventKind.FRAMES_JUMPED]
    assert (events[0].frame_index, events[0].timestamp) == (7, 7 / RATE_HZ)
    assert events[0].details == {"from_frame": 7, "to_frame": 3, "direction": "backward", "frames": 5,
                                 "source": "script"}


def test_a_forward_jump_skips_frames_without_reading_them():
    sequence = frames(12, first_index=100)  # frame numbers of a sequence cut to start at frame 100
    seen, events = play_all(Player(sequence, jumps=[(103, 108)]))
    assert seen == [100, 101, 102, 103] + list(range(108, 112))
    assert sequence.reads == seen
    assert events[0].details == {"from_frame": 103, "to_frame": 108, "direction": "forward", "frames": 4,
                                 "source": "script"}


def test_drops_and_jumps_are_one_mechanism_each_scripted_move_once_per_pass():
    seen, events = play_all(Player(frames(10), drops=[(2, 2)], jumps=[(6, 1), (6, 8)]))
    # 2-3 dropped; after 6 back to 1 (2 is not dropped again); after 6 again on to 8 (the second jump from 6).
    assert seen == [0, 1, 4, 5, 6, 1, 2, 3, 4, 5, 6, 8, 9]
    assert [(e.kind, e.frame_index) for e in events] == [
        (EventKind.FRAMES_DROPPED, 2), (EventKind.FRAMES_JUMPED, 6), (EventKind.FRAMES_JUMPED, 6)]
    assert [e.details.get("to_frame") for e in events[1:]] == [1, 8]


def test_live_jump_back_continues_before_the_last_frame_handed_out():
    player = Player(frames(10))
    seen, events = [], []
    for frame in player.play(on_event=events.append):
        seen.append(frame.index)
        if len(seen) == 7:  # frame 6, the first time
            player.jump_back(4)  # a click on the page while frame 6 is being tracked
    assert seen == list(range(7)) + list(range(2, 10))
    assert events[0].details == {"from_frame": 6, "to_frame": 2, "direction": "backward", "frames": 5,
                                 "source": "live"}


def test_a_jump_back_stops_at_the_first_frame():
    player = Player(frames(6))
    seen = []
    for frame in player.play():
        seen.append(frame.index)
        if len(seen) == 2:
            player.jump_back(50)
    assert seen == [0, 1, 0, 1, 2, 3, 4, 5]


@pytest.mark.parametrize("jump", [(-1, 2), (3, -1)])
def test_invalid_scripted_jumps_are_refused(jump):
    with pytest.raises(ValueError, match="jump"):
        Player(frames(5), jumps=[jump])


def test_a_jump_to_a_frame_outside_the_sequence_is_refused():
    with pytest.raises(ValueError, match="not in the sequence"):
        Player(frames(5)).jump_to(9)


def test_playing_time_leaves_out_pauses():
    player = Player(frames(40))
    player.speed = 4.0  # 40 frames at 20 Hz: 0.5 s of playing
    consumer = Consumer(player)
    assert consumer.next() == 0
    player.pause()
    time.sleep(0.5)
    player.resume()
    while consumer.next() is not None:
        pass
    assert 0.4 < player.playing_time() < 0.8  # the 0.5 s pause is not in it


def late_start(player: Player) -> tuple[list[int], list]:
    """A tracker that spends 7 frame intervals on the first frame, then keeps up: frames 1-6 (at least) arrive while
    it is busy and are dropped as late."""
    seen, events = [], []
    for frame in player.play(on_event=events.append):
        seen.append(frame.index)
        if frame.index == 0:
            time.sleep(7 / RATE_HZ)
    return seen, events


def test_realtime_a_scripted_drop_at_a_late_frame_still_hides_what_it_covers():
    seen, events = late_start(Player(frames(30), drops=[(5, 10)], realtime=True))
    assert seen[0] == 0 and not set(seen) & set(range(1, 15))  # 5-14 hidden by the drop, 1-6 (or more) late
    assert seen[1:] == list(range(15, 30))
    dropped = [(event.details["source"], event.details["count"]) for event in events]
    assert [source for source, _ in dropped] == ["realtime", "script"]
    assert sum(count for _, count in dropped) == 14


def test_realtime_a_scripted_jump_at_a_late_frame_still_jumps():
    seen, events = late_start(Player(frames(30), jumps=[(3, 20)], realtime=True))
    assert seen == [0, *range(20, 30)]
    assert [event.kind for event in events] == [EventKind.FRAMES_DROPPED, EventKind.FRAMES_JUMPED]
    assert events[1].details["source"] == "script" and events[1].details["to_frame"] == 20
