"""Frames with what the Player reads of a sequence (frame numbers, timestamps, ``cut``), for tests that script
the frames themselves."""

from __future__ import annotations


class FakeSequence:
    """Frames (anything with ``index`` and ``timestamp``) in playing order. ``reads`` lists the frame numbers handed
    out by iteration, cuts included, so that a test can tell which frames were read."""

    def __init__(self, frames, reads: list[int] | None = None):
        self.frames = list(frames)
        self.reads = [] if reads is None else reads

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, position: int):
        return self.frames[position]

    @property
    def indices(self) -> list[int]:
        return [frame.index for frame in self.frames]

    @property
    def timestamps(self) -> list[float]:
        return [frame.timestamp for frame in self.frames]

    def cut(self, start: int) -> "FakeSequence":
        return FakeSequence(self.frames[start:], self.reads)

    def __iter__(self):
        for frame in self.frames:
            self.reads.append(frame.index)
            yield frame
