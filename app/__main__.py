"""``python -m app`` and the ``fdmo`` command (``main``).

The command's entry point is here rather than in app.cli because a process that multiprocessing spawns (the feature
half's, vo_core/features/feature_process.py) first runs its parent's script again, and the ``fdmo`` script imports
the module of its entry point: from app.cli that was all of the app and the odometry (0.67 s of imports in the new
process, on top of the 0.5 s the feature half needs); from here it is nothing. (``python -m app`` runs this file as
``__main__``, which multiprocessing does not run again.) Before anything is imported, a run whose feature half maps
in a process of its own starts that process (app/process_start.py).
"""

import sys


def main() -> int:
    from app.process_start import start_feature_process

    start_feature_process(sys.argv[1:])  # first: it gets ready while the rest is imported
    from app.cli import command_line

    return command_line()


if __name__ == "__main__":
    sys.exit(main())
