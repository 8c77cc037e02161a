"""The whole configuration: typed dataclasses with the papers' values as defaults, loaded from YAML.

Each half keeps its settings in its own dataclass (``vo_core/<half>/config.py``); this module composes
them, reads YAML and ``key=value`` overrides onto them, and dumps the resolved result beside the outputs.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vo_core.direct.config import DirectConfig
from vo_core.direct.divergence import DivergenceConfig
from vo_core.errors import InputError
from vo_core.features.config import FeatureConfig
from vo_core.front_ends.klt.config import KltConfig
from vo_core.init.config import InitConfig
from vo_core.yaml_input import parse_yaml

METHODS = ("fdmo", "direct", "features", "klt")


@dataclass
class DatasetConfig:
    on_bad_image: str = "skip"  # "skip": drop an unreadable image with an event; "abort": stop with an error
    read_ahead: int = 8  # frames decoded ahead on a background thread
    undistort_output: str = "crop"  # DSO's choices: "crop", "full", "none" or "WxH"


@dataclass
class HybridConfig:
    """How the system lets the two halves work together (FDMO sections 4.2.1-4.2.2, Figs. 2 and 3)."""

    divergence: DivergenceConfig = field(default_factory=DivergenceConfig)
    # A direct pose agrees with the feature map's pose when it explains the majority of that pose's inlier matches (by
    # the same chi-square test): most of the feature map's evidence then puts the camera where the direct pose does.
    # One threshold wherever the feature map confirms a direct pose: a suspect frame's, a new direct keyframe's
    # (decide.judge_keyframe), the alignment from a recovered pose (decide.after_recovery). Recorded: poses the feature
    # map confirmed explained 97-99.5 % of its matches (teddy); the direct keyframes of right maps 69 % or more on the
    # real-data matrix (teddy, KITTI, parking and the drone clip at strides 1-3); wrong ones: the pose locked 20 cm off
    # after teddy's 20-frame drop 41 %, fr1/desk's keyframes where its direct scale collapsed 10x 34-55 %. The majority
    # replaced two thresholds of ours (80 % for a suspect frame, 50 % for a keyframe; at 80 % for both, teddy at a
    # third of its frame rate and the drone clip at half restarted right maps, 0.0083 -> 0.0121 m and 0.060 -> 0.226 m
    # at one seed); on the matrix (5 folders x strides 1-3 x 3 seeds) 42 of 45 runs stayed the same to the byte and
    # fr1/desk's other three within their seeds' spread.
    agreement: float = 0.5
    # A conclusive recovery puts the camera at another place than a direct pose that explains less than this share
    # of its inlier matches (ours: where a direct pose was right beside a feature pose off by the map's own error, it
    # explained 29-72 % of them; one 10.9 m off after parking was played back 70 frames, none). Such a direct pose is
    # not kept after the recovery, whatever its photometric fit.
    elsewhere_share: float = 0.2
    # After a recovery, direct alignment is tried again from the recovered pose. Where it ends at the pose the
    # motion model's alignment reached, both starts found the same optimum: the direct pose was right and tracking
    # goes on in the same window. The same, as far as the feature map can tell: the recovery's inliers move between
    # the two poses by less than the bound of the test that judges its measurements (ORB-SLAM2's chi-square at 95 %,
    # 2 DOF, at level 0: sqrt(5.991) px, features.mapping.chi2_two_dof; it was 1 px of ours, and on the real-data
    # matrix, the drops, the faults and the forward-and-back runs no decision fell between the two). Restarting where
    # both met cost: teddy with 15 frames dropped at 140 and parking with 10 at 100, the recovered poses were up to 9 cm
    # off and restarting at them cost 6-9x the ATE; on teddy played forward and back 0.010 -> 0.023 m. The feature
    # pose's disagreement is not asked for: it is the feature map's own error (the direct pose explained 29-79 % of the
    # recovery's inliers where it was the better pose).
    same_optimum_px: float = 2.45
    # After missed frames, a direct pose that nothing confirms (no feature pose, or one too weak to overrule it) is
    # kept only where it lies within this share of the image motion that the last motion, kept up over the time
    # that passed, predicts, from the predicted pose (ours: half). Further, it is the tracker's lock onto the view it
    # left, the classic failure of direct alignment after a large jump: parking with 9.15 m dropped, the direct pose
    # stayed by the look-alike parked cars the camera had passed and every later frame was 9.1 m off, reported
    # only as unverified; with 3.15 m dropped the right direct pose lay 0.3 px from the prediction.
    gap_motion_share: float = 0.5
    # A recovery, or a direct pose the feature map confirms, is held to the same prediction where the motion has been
    # predictable (where the view repeats, the feature map finds the same look-alike place that direct alignment
    # locks onto): the median relative error of the one-frame predictions over the last prior_frames posed frames
    # (at least min_prior_frames of them), times the square root of the intervals missed, at most this (ours:
    # half of gap_motion_share, so that the prediction's own error leaves the rule its margin).
    prior_reliability: float = 0.25
    prior_frames: int = 20
    min_prior_frames: int = 5
    # Frames in a row without a pose (no direct tracking, no recovery) before the direct map initializes again
    # from scratch, at a new scale (ours; recovery keeps being tried meanwhile, and after).
    lost_frames_before_reinitialization: int = 10
    # A direct map restarted at a recovered pose takes its depths from the feature points in view, as many as a start
    # needs (init.two_view.min_triangulated, ORB-SLAM's 50), of points observed by at least this many keyframes: a
    # point seen by two is as uncertain in depth as their baseline makes it (ORB-SLAM2's MapPointCulling keeps a
    # monocular point only once more than 2 keyframes see it).
    # Teddy, 13 frames missed right after the start: a restart on the start's 75 two-view points (3 frames apart)
    # collapsed the scale 10x, unreported (ATE 0.09-0.13 m at 3 seeds of 4; the same window: 0.005-0.006 m). With
    # fewer, the better fit of the two direct alignments goes on in the same window.
    min_restart_observations: int = 3


@dataclass
class MappingConfig:
    """Where mapping runs (vo_core/mapping_thread.py). Synchronous mapping is deterministic (the same input gives
    the same trajectory) and the default of runs, experiments and benches; ``fdmo run --realtime`` and ``--viser``
    run it on its own thread, as DSO's multi-threaded mode does, so that tracking keeps up with the camera."""

    threaded: bool = False
    # With mapping threads, tracking either waits while a keyframe is being mapped, and every frame is traced
    # (offline: nothing is lost by waiting, and the maps are the synchronous run's), or goes on, and a later frame
    # becomes the keyframe once the mapper is free (live input, DSO's real-time mode: fewer keyframes where mapping
    # is slow, instead of frames missed while waiting).
    wait_for_keyframes: bool = True
    # DSO's mappingLoop, live: with more than 3 frames waiting, the mapper catches up (frames no longer traced).
    max_queued_frames: int = 3
    # The feature half's process (features/feature_process.py) runs this much nicer than tracking and the direct
    # mapper: it is behind neither (tracking waits for the direct reference, the feature map only has to keep up),
    # so on a busy machine the cores go to them first. 0: the same priority. Offline the feature map is only waited
    # for before a recovery and at the end (19: the window optimization ran 20 % longer beside it at 10). Live, a
    # suspect frame's check and every recovery wait for it while frames arrive, so it runs at tracking's own
    # priority: a nicer process that tracking waits for is a priority inversion, and any other work on the machine
    # takes the cores from it while tracking waits (teddy at 30 Hz beside one busy process, 4 runs each: at 10, 10 %
    # of the frames processed and every run lost, 0.26 m; at 0, 71 % and none lost, 0.011 m). BENCHMARKS.md: Live.
    feature_niceness: int = 19
    live_feature_niceness: int = 0
    # Offline the feature process also runs in Linux's idle scheduling class (SCHED_IDLE), below any niceness: at 19
    # alone, parking's window optimizations took 3.44 s beside it against 2.87 s without it; idle, 3.1 s (threaded
    # runs, 4 rounds: teddy 8.72 -> 8.48 s, parking 10.33 -> 10.16 s, KITTI the same). Not live, where a suspect
    # frame's check waits for the feature map.
    feature_idle_scheduling: bool = True
    # How often Python lets another thread take the interpreter lock (sys.setswitchinterval) while mapping threads
    # run; Python's own 5 ms made tracking wait up to 5 ms each time it came back from a compiled kernel while the
    # mapper ran Python (tracking does that a dozen times a frame). Measured in BENCHMARKS.md (Real time).
    switch_interval_s: float = 0.0002


@dataclass
class Config:
    method: str = "fdmo"  # FDMO: direct odometry, the feature map beside it, divergence test and recovery
    seed: int = 0  # every random choice (RANSAC, sampling) draws from generators seeded with this
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    klt: KltConfig = field(default_factory=KltConfig)
    direct: DirectConfig = field(default_factory=DirectConfig)
    init: InitConfig = field(default_factory=InitConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    fdmo: HybridConfig = field(default_factory=HybridConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    """Convert a YAML or command-line value to the annotated type, or say which key is wrong and what it takes."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
        origin = typing.get_origin(annotation)
    if origin in (list, tuple):
        return _coerce_items(value, annotation, key)
    if annotation not in _SCALARS:
        return value
    convert, expected = _SCALARS[annotation]
    try:
        return convert(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"config key '{key}': cannot read {value!r} as {expected}") from None


def _coerce_items(value: Any, annotation: Any, key: str) -> list | tuple:
    """A list from YAML (``[1, 2]``, also as the text of --set); ``tuple[float, float]`` fixes its length."""
    if isinstance(value, str):
        value = parse_yaml(value, f"config key '{key}'", numbered=False)
    item_types = typing.get_args(annotation)
    fixed_length = len(item_types) if item_types and Ellipsis not in item_types else None
    if not isinstance(value, (list, tuple)) or fixed_length not in (None, len(value)):
        expected = f"a list of {fixed_length}" if fixed_length else "a list"
        raise InputError(f"config key '{key}': cannot read {value!r} as {expected}")
    items = [item if not item_types else _coerce(item, item_types[0], key) for item in value]
    return tuple(items) if typing.get_origin(annotation) is tuple else items


def _boolean(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    text = str(value).lower() if isinstance(value, (str, int)) else None
    if text in ("true", "1", "yes", "on"):
        return True
    if text in ("false", "0", "no", "off"):
        return False
    raise ValueError(value)


def _integer(value: Any) -> int:
    if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
        raise ValueError(value)  # 2.5 is no count, and true no number
    return int(value)


def _number(value: Any) -> float:
    if isinstance(value, bool):
        raise ValueError(value)
    return float(value)


def _text(value: Any) -> str:
    if value is None or isinstance(value, (dict, list)):
        raise ValueError(value)
    return str(value)


# annotation -> (conversion, what the error message says it takes)
_SCALARS = {bool: (_boolean, "true or false"), int: (_integer, "an integer"), float: (_number, "a number"),
            str: (_text, "text")}


def _apply(obj: Any, values: dict[str, Any], prefix: str, source: str) -> None:
    hints = _field_types(type(obj))
    for name, value in values.items():
        key = f"{prefix}{name}"
        if name not in hints:
            raise InputError(f"{source}: unknown config key '{key}'")
        current = getattr(obj, name)
        if dataclasses.is_dataclass(current):
            if value is None:  # a section left empty (all of its keys commented out)
                continue
            if not isinstance(value, dict):
                raise InputError(f"{source}: config key '{key}' is a section, got {value!r}")
            _apply(current, value, key + ".", source)
        else:
            setattr(obj, name, _coerce(value, hints[name], key))


def _validate(config: Config) -> None:
    if config.method not in METHODS:
        raise InputError(f"config key 'method': {config.method!r} is not one of {', '.join(METHODS)}")


def load_config(path: str | Path | None = None, overrides: list[str] | None = None) -> Config:
    """Defaults, then the YAML file, then ``key.sub=value`` overrides (as from ``--set``)."""
    config = Config()
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: config file not found")
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as error:
            raise InputError(f"{path}: cannot read ({error.__class__.__name__})") from None
        values = parse_yaml(text, str(path)) or {}
        if not isinstance(values, dict):
            raise InputError(f"{path}: the config must be a mapping of keys to values")
        _apply(config, values, "", str(path))
    for item in overrides or []:
        if "=" not in item:
            raise InputError(f"--set {item}: expected key=value")
        key, raw = item.split("=", 1)
        nested: dict[str, Any] = {}
        cursor = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        cursor[parts[-1]] = parse_yaml(raw, f"--set {item}", numbered=False) if raw.strip() else raw
        _apply(config, nested, "", f"--set {item}")
    _validate(config)
    return config


def config_to_dict(config: Config) -> dict[str, Any]:
    return dataclasses.asdict(config)


def dump_config(config: Config, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))
