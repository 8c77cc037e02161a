"""Settings of the classic KLT baseline (paper 003). Filled in by the KLT issue."""

from dataclasses import dataclass


@dataclass
class KltConfig:
    pass
