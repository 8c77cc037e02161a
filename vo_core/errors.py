"""Errors for bad input. The CLI turns them into a one-line message and exit code 2, never a traceback."""


class InputError(Exception):
    """Bad user input: a missing or corrupt file, an unknown layout, malformed calibration or config.

    The message names the offending file (or option) and says what is wrong with it, on one line."""
