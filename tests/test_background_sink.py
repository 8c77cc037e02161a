"""BackgroundSink (app/sinks/background.py): the wrapped sink gets every call, in order, on a thread of its own,
and its failures reach the caller."""

from __future__ import annotations

import threading

import pytest

from app.sinks.background import BackgroundSink


class RecordingCalls:
    def __init__(self, fail_on: str | None = None):
        self.calls: list[tuple[str, object]] = []
        self.threads: set[str] = set()
        self.fail_on = fail_on

    def _note(self, name: str, value: object = None) -> None:
        self.threads.add(threading.current_thread().name)
        if name == self.fail_on:
            raise RuntimeError(f"{name} failed")
        self.calls.append((name, value))

    def on_frame(self, frame, result):
        self._note("frame", frame)

    def on_event(self, event):
        self._note("event", event)

    def on_map(self, snapshot):
        self._note("map", snapshot)

    def restart(self):
        self._note("restart")

    def close(self):
        self._note("close")


def test_every_call_arrives_in_order_on_another_thread_and_close_waits_for_them():
    inner = RecordingCalls()
    sink = BackgroundSink(inner, max_queued=2)  # a short queue: the caller waits for room
    for i in range(50):
        sink.on_frame(i, None)
        if i % 10 == 0:
            sink.on_event(f"event {i}")
            sink.on_map(f"map {i}")
    sink.restart()
    sink.close()
    expected = []
    for i in range(50):
        expected.append(("frame", i))
        if i % 10 == 0:
            expected += [("event", f"event {i}"), ("map", f"map {i}")]
    assert inner.calls == expected + [("restart", None), ("close", None)]
    assert inner.threads == {"RecordingCalls"} != {threading.current_thread().name}


def test_a_failure_of_the_sink_is_raised_on_the_callers_thread_once_and_the_sink_gets_no_more_calls():
    inner = RecordingCalls(fail_on="map")
    sink = BackgroundSink(inner)
    sink.on_frame(0, None)
    with pytest.raises(RuntimeError, match="map failed"):  # at the next call or at close: the thread decides
        sink.on_map("map")
        sink.on_frame(1, None)
        sink.close()
    sink.close()  # raised once: the rest of the queue goes, unseen
    assert inner.calls == [("frame", 0)]  # neither frame 1 nor close reached a sink in an unknown state
