"""The first run's kernel builds are announced once and left out of the frame rates (app/kernel_build.py)."""

from __future__ import annotations

import json
import time

import numba
import numpy as np
import pytest

import vo_core.system
from app.cli import main
from app.kernel_build import KernelBuilds, kernel_build_seconds, kernel_builds_announced, playing_clock
from test_cli import ScriptedFrontEnd, dataset  # noqa: F401 (dataset: the fixture, a tiny VAMR folder)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_nested_builds_count_once_and_the_announcement_comes_once():
    clock, said = FakeClock(), []
    builds = KernelBuilds(announce=lambda: said.append(clock.now), clock=clock)
    clock.now = 1.0
    builds.started()  # a kernel...
    clock.now = 2.0
    builds.started()  # ...that calls another, built inside it
    clock.now = 4.0
    builds.ended()
    assert builds.seconds() == pytest.approx(3.0)  # the build under way counts
    clock.now = 5.0
    builds.ended()
    clock.now = 9.0
    builds.started()
    clock.now = 10.0
    builds.ended()
    assert builds.seconds() == pytest.approx(5.0) and said == [1.0]


def fresh_kernel():
    """A kernel numba has never built in this process (no cache), so that calling it builds it."""

    @numba.njit(cache=False)
    def sum_of_squares(values):
        total = 0.0
        for value in values:
            total += value * value
        return total

    return sum_of_squares


def test_a_real_build_is_timed_and_the_playing_clock_stands_still_meanwhile():
    said = []
    with kernel_builds_announced(lambda: said.append(True)):
        before, clock_before = kernel_build_seconds(), playing_clock()
        wall_before = time.monotonic()
        assert fresh_kernel()(np.arange(4.0)) == 14.0
        built = kernel_build_seconds() - before
        assert playing_clock() - clock_before == pytest.approx(time.monotonic() - wall_before - built, abs=0.01)
    fresh_kernel()(np.arange(4.0))  # built after the block: not announced
    assert built > 0.0 and said == [True]


def test_a_run_that_builds_a_kernel_says_so_once_and_leaves_it_out_of_the_fps(dataset, tmp_path, capsys,
                                                                              monkeypatch):
    kernels = [fresh_kernel(), fresh_kernel()]
    calls = {2: lambda: kernels[0](np.ones(3)), 4: lambda: kernels[1](np.ones(3))}  # two builds, one announcement
    monkeypatch.setattr(vo_core.system, "make_front_end",
                        lambda config, camera, start_witness: ScriptedFrontEnd(at_frame=calls))
    assert main(["run", str(dataset), "--out", str(tmp_path / "out"), "--no-rrd"]) == 0
    err = capsys.readouterr().err
    assert err.count("fdmo: building the compiled kernels, once") == 1
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["kernel_build_s"] > 0.0
    assert metrics["playing_s"] == pytest.approx(metrics["wall_s"] - metrics["kernel_build_s"], abs=0.05)
