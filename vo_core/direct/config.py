"""Settings of the direct half (DSO, Engel et al. 2017; FDMO section 4.2.1). Filled in by the direct issues."""

from dataclasses import dataclass


@dataclass
class DirectConfig:
    pass
