"""A reader of the PLY files the results hold, written from the format's definition (paulbourke.net/dataformats/ply)
rather than with the writer's code, so that a test of the writer can fail."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, colors) of a binary little-endian PLY with float x y z and uchar red green blue."""
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    lines = header.decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    types = {"float": "<f4", "uchar": "u1"}
    properties = [line.split()[1:] for line in lines if line.startswith("property")]
    assert [name for _, name in properties] == ["x", "y", "z", "red", "green", "blue"]
    vertices = np.frombuffer(body, dtype=[(name, types[kind]) for kind, name in properties], count=count)
    assert len(body) == vertices.nbytes
    return (np.column_stack([vertices[a] for a in "xyz"]).astype(float),
            np.column_stack([vertices[c] for c in ("red", "green", "blue")]))
