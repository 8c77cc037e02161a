"""``python -m app`` is the ``fdmo`` command."""

import sys

from app.cli import command_line

sys.exit(command_line())
