"""The experiments of FDMO section 5 as commands (``fdmo experiment NAME SOURCE``), one module each:

- ``frame-drop`` (frame_drop.py): sec. 5.3.2 and Fig. 6, jumps forward and back by growing numbers of frames;
- ``two-loop`` (two_loop.py): sec. 5.3.1 and Table 3, the sequence played twice, TUM monoVO drifts per loop;
- ``timing`` (timing.py): sec. 5.2 and Table 2, the time of each process per method.

Each writes a folder (the experiment's settings, each method's resolved configuration, the raw results as CSV,
table.md, the plots) and prints its table; common.py holds what they share.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from app.experiments import frame_drop, timing, two_loop
from app.experiments.common import add_common_arguments

EXPERIMENTS = {module.NAME: module for module in (frame_drop, two_loop, timing)}


def add_experiment_parsers(parser: argparse.ArgumentParser, parser_class: type,
                           add_source_options: Callable[[argparse.ArgumentParser], None]) -> None:
    """``fdmo experiment NAME SOURCE ...``: a subcommand per experiment, with the options they share, the dataset
    options of ``fdmo run`` (``add_source_options``) and its own."""
    names = parser.add_subparsers(dest="experiment", required=True, parser_class=parser_class)
    for name, module in EXPERIMENTS.items():
        command = names.add_parser(name, help=module.HELP, description=module.__doc__.split("\n\n")[0])
        add_common_arguments(command)
        add_source_options(command)
        module.add_arguments(command)


def run_experiment(args: argparse.Namespace) -> None:
    EXPERIMENTS[args.experiment].run(args)
