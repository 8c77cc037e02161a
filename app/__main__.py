"""``python -m app`` is the ``fdmo`` command."""

import sys

from app.cli import main

sys.exit(main())
