"""``python -m app`` is the ``fdmo`` command."""

import sys

from app.cli import command_line

if __name__ == "__main__":  # not when a spawned process (the feature map's) imports it again
    sys.exit(command_line())
