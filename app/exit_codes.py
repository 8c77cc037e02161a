"""fdmo's exit codes, one convention for every command: 0 on success, 2 on bad input, 128 + the signal's number
when a signal cut the work short (the shell's convention: 130 for SIGINT, Ctrl-C; 143 for SIGTERM, a timeout or a
job scheduler), 141 when the reader of the output went away (SIGPIPE's)."""

from __future__ import annotations

import signal

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 128 + signal.SIGINT  # 130
EXIT_TERMINATED = 128 + signal.SIGTERM  # 143
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # 141
INTERRUPTED_CODES = (EXIT_INTERRUPTED, EXIT_TERMINATED)


def exit_code_of_signal(signum: int) -> int:
    """What a command that a signal stopped exits with (after finishing its files)."""
    return 128 + int(signum)
