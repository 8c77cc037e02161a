"""The KLT baseline, ``--method klt`` (paper 003): pipeline.py, its bootstrap, state and settings. The corner
detection and KLT tracking it shares with the feature initializer are vo_core/geometry/klt.py."""
