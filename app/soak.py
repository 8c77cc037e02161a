"""A long run of a looping synthetic sequence through the odometry with the Rerun recording on (issue 17): does
anything grow with the number of frames?

    report = soak(frames=10_000, width=640, height=480, out_dir=Path("results/soak"))

Every ``sample_every`` frames: the process's resident memory (RSS) and its peak so far, the maps as the odometry
reports them at its keyframes (direct keyframes and points, feature keyframes and points) and the size of the
recording so far (all its parts). The memory is flat when every sample after the first stays within
``RSS_TOLERANCE`` of the first (the first is taken once the loop's frames are cached, the kernels loaded and the
window full), and the peak of the whole run, the recording closed, within ``RSS_TOLERANCE`` of the peak after the
first ``REFERENCE_FRAMES`` frames (issue 48).
``benchmarks/soak.py`` runs 10,000 frames; tests/test_soak.py 1,000.
"""

from __future__ import annotations

import resource
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil

from app.pipeline import RunSummary, run_sequence
from app.sinks.recording_parts import PART_FRAMES, recording_files
from app.sinks.rerun_sink import RerunSink
from vo_core.config import Config, load_config
from vo_core.events import Event, FrameResult, MapSnapshot
from vo_core.synthetic import make_sequence
from vo_core.synthetic.faults import looping

RSS_TOLERANCE = 0.10  # issue 17: within 10 % of the value after the first samples
REFERENCE_FRAMES = 1000  # issue 48: the peak of a long run within RSS_TOLERANCE of its value after 1,000 frames
LOOP_FRAMES = 300  # one turn of the "loop" preset: 10 s at 30 Hz (its frames are rendered once and kept)
RECORDING_FILE = "recording.rrd"
MB = 2**20


@dataclass
class SoakSample:
    frames: int  # frames processed so far
    rss_mb: float
    peak_mb: float  # the process's peak RSS so far
    direct_keyframes: int
    direct_points: int
    feature_keyframes: int
    feature_points: int
    recording_bytes: int  # the size of the recording's files so far (written as the run goes)


@dataclass
class SoakReport:
    samples: list[SoakSample]
    summary: RunSummary
    recording_files: list[Path]  # the recording's parts (recording.rrd, recording.part2.rrd, ...), closed
    final_peak_mb: float  # the process's peak RSS over the whole run, the recording's files closed

    @property
    def recording_bytes(self) -> int:
        return sum(path.stat().st_size for path in self.recording_files)

    @property
    def bytes_per_frame(self) -> float:
        return self.recording_bytes / max(self.summary.metrics["processed_frames"], 1)

    @property
    def rss_drift(self) -> float:
        """The largest relative distance of a sample's RSS from the first sample's."""
        first = self.samples[0].rss_mb
        return max(abs(sample.rss_mb - first) / first for sample in self.samples)

    @property
    def rss_flat(self) -> bool:
        return self.rss_drift <= RSS_TOLERANCE

    @property
    def peak_growth(self) -> float | None:
        """How much the run's peak RSS grew after the first REFERENCE_FRAMES frames, relative to the peak then (None
        when no sample was taken there)."""
        reference = next((s.peak_mb for s in self.samples if s.frames >= REFERENCE_FRAMES), None)
        return None if reference is None else (self.final_peak_mb - reference) / reference

    @property
    def peak_flat(self) -> bool:
        return self.peak_growth is None or self.peak_growth <= RSS_TOLERANCE


class _Sampler:
    """A sink that samples memory, map sizes and the recording's size every ``every`` frames."""

    def __init__(self, every: int, recording: Path | None):
        self.every = every
        self.recording = recording
        self.frames = 0
        self.samples: list[SoakSample] = []
        self._map = MapSnapshot()
        self._process = psutil.Process()

    def on_frame(self, frame: Any, result: FrameResult) -> None:
        self.frames += 1
        if self.frames % self.every == 0:
            self.samples.append(SoakSample(
                self.frames, self._process.memory_info().rss / MB, peak_rss_mb(), len(self._map.keyframe_poses),
                _count(self._map.direct_points_world), len(self._map.feature_keyframe_poses),
                _count(self._map.feature_points_world), _size(self.recording)))

    def on_map(self, snapshot: MapSnapshot) -> None:
        self._map = snapshot

    def on_event(self, event: Event) -> None:
        pass

    def close(self) -> None:
        pass


def soak(frames: int, width: int, height: int, out_dir: Path, config: Config | None = None,
         sample_every: int = 500, loop_frames: int = LOOP_FRAMES, recording: bool = True, seed: int = 0,
         part_frames: int = PART_FRAMES) -> SoakReport:
    """``frames`` frames of the "loop" preset (``loop_frames`` per turn, rendered once) through ``config.method``
    (default: fdmo), the Rerun recording written to ``out_dir``/recording.rrd (a new part every ``part_frames``
    frames, 0: one file) unless ``recording`` is False."""
    config = config or load_config()
    sequence = looping(make_sequence("loop", loop_frames, seed=seed, width=width, height=height), frames)
    path = Path(out_dir) / RECORDING_FILE if recording else None
    sampler = _Sampler(sample_every, path)
    sinks = [sampler]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        sinks.append(RerunSink(path, sequence.camera, ground_truth=sequence.ground_truth,
                               recording_name=sequence.name, part_frames=part_frames))
    summary = run_sequence(sequence, config, out_dir, sinks)
    return SoakReport(sampler.samples, summary, [] if path is None else recording_files(path), peak_rss_mb())


def _count(points) -> int:
    return 0 if points is None else len(points)


def _size(path: Path | None) -> int:
    return 0 if path is None else sum(part.stat().st_size for part in recording_files(path))


def peak_rss_mb() -> float:
    """The process's peak resident memory so far (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def rss_samples_text(report: SoakReport) -> str:
    """One line per sample, for logs and test failures."""
    return "\n".join(f"{s.frames:6d} frames: {s.rss_mb:7.1f} MB RSS (peak {s.peak_mb:.1f}), keyframes "
                     f"{s.direct_keyframes} direct / {s.feature_keyframes} feature, points {s.direct_points} / "
                     f"{s.feature_points}, recording {s.recording_bytes / MB:.1f} MB" for s in report.samples)
