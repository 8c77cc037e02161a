"""What the ``fdmo`` command starts before it imports the odometry (app/__main__.py calls it first).

A threaded fdmo run maps its feature half in a process of its own (vo_core/features/feature_process.py), which
needs about 0.8 s of CPU before it can map: its imports, numba's start, its compiled kernels loaded. Started when the
odometry is built, that start delayed the run's first keyframes (teddy's first checked frame waited 0.2-0.3 s for
the feature map); started before this process's own imports (0.6 s, on one core), it runs on the other core.

This module imports nothing of the app or the odometry: it reads the command line by hand.
"""

from __future__ import annotations

from collections.abc import Sequence

MAPPING_MODES = ("sync", "threaded")
# vo_core.config.Config.method's default, which this module must not import (tests/test_cli.py holds them equal).
DEFAULT_METHOD = "fdmo"
FEATURE_MAP_METHOD = "fdmo"  # the method with a feature half


def mapping_mode(mapping: str | None, realtime: bool, viser: bool) -> str:
    """``--mapping``, or its default: on its own thread with ``--realtime`` (a live camera's runs too) and with
    ``--viser``, on the tracking thread otherwise."""
    return mapping or ("threaded" if realtime or viser else "sync")


def start_feature_process(argv: Sequence[str]) -> None:
    """Starts the feature half's process ahead of the odometry when the command line asks for a run that will have
    one."""
    if maps_features_in_a_process(argv):
        from vo_core.features.feature_process import start_ahead

        start_ahead()


def maps_features_in_a_process(argv: Sequence[str]) -> bool:
    """Whether ``argv`` (without the program) is an fdmo run with mapping threads, read from its options alone. A
    ``--config`` or ``--set`` that says otherwise leaves a process started in vain (it waits, idle, and ends with
    this one) or none started ahead (the odometry then starts it, as without this); a live camera's run starts
    one in its warm-up (app.pipeline.warm_up)."""
    if not argv or argv[0] != "run":
        return False
    method = _last_value(argv, "--method") or DEFAULT_METHOD
    mode = mapping_mode(_last_value(argv, "--mapping"), "--realtime" in argv, "--viser" in argv)
    return method == FEATURE_MAP_METHOD and mode == "threaded"


def _last_value(argv: Sequence[str], option: str) -> str | None:
    """The value of the last ``option VALUE`` or ``option=VALUE`` in ``argv`` (argparse's rule: the last wins)."""
    value = None
    for position, argument in enumerate(argv):
        name, equals, given = argument.partition("=")
        if name == option:
            value = given if equals else (argv[position + 1] if position + 1 < len(argv) else None)
    return value
