"""Settings of the feature-based initializer (paper 004). Filled in by the initializer issue."""

from dataclasses import dataclass


@dataclass
class InitConfig:
    pass
