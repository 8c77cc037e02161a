"""YAML the user wrote (a --config file, a camera.yaml, EuRoC's sensor.yaml, a --set value), read with one kind of
error: the source, the line where the parser stopped, and what it expected."""

from __future__ import annotations

from typing import Any

import yaml

from vo_core.errors import InputError


def parse_yaml(text: str, source: str, numbered: bool = True) -> Any:
    """``text`` as YAML; malformed, an InputError ``source:LINE: malformed YAML (problem)`` (``numbered=False``:
    no line, for a one-line value such as a --set's)."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f":{mark.line + 1}" if numbered and mark is not None else ""
        problem = getattr(error, "problem", None) or str(error).splitlines()[0]
        raise InputError(f"{source}{where}: malformed YAML ({problem})") from None
