"""The matrix of ``fdmo bench``: which sequences, methods, seeds, settings and tasks, read from YAML.

    sequences:                     # dataset folders, videos, synthetic:PRESET[:FRAMES[:WxH]], or "bundled"
      - ../shared/data/tum_fr3_teddy_first200
      - {path: ../shared/data/kitti00_first100, name: kitti, format: kitti, end: 50}
    methods: [fdmo, direct, klt]
    strides: [1, 2, 3]             # each sequence also played every 2nd and 3rd frame (--stride), as the sequences
                                   # NAME.stride2 and NAME.stride3 (default: [1]); a sequence may set its own stride
    seeds: [0, 1, 2]               # config.seed of each cell (default: [0])
    settings:                      # named sets of --set overrides, a cell each (default: one set, no override)
      default: {}
      coarse: {direct.initializer: coarse}
    tasks:                         # what each cell runs (default: [run])
      - run                        # fdmo run: ATE, RPE, tracked fraction, initialization frame, fps, events
      - two-loop                   # fdmo experiment two-loop
      - {task: frame-drop, name: drop-at-100, args: [--at, "100", --direction, forward]}
    timeout_s: 3600                # a cell still running after this long is stopped and reported

A cell is one sequence x method x setting x task x seed, run as its own process. Relative paths are taken from
the working directory, as on the command line, and made absolute for the cells (which run in their own folders,
on a cluster on other machines: there the paths must name the same files).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import yaml

from vo_core.datasets import DEFAULT_SEQUENCE
from vo_core.errors import InputError
from vo_core.system import IMPLEMENTED_METHODS

BUNDLED = "bundled"  # the sequence shipped with the package: what `fdmo run` plays without an argument
SYNTHETIC_PREFIX = "synthetic:"
TASKS = ("run", "frame-drop", "two-loop")  # fdmo run, fdmo experiment frame-drop, fdmo experiment two-loop
DEFAULT_TIMEOUT_S = 3600.0
SOURCE_OPTIONS = {"format": "--format", "camera": "--camera", "gt": "--gt"}  # of fdmo run and fdmo experiment
PATH_OPTIONS = ("camera", "gt")
NAME_CHARACTERS = "A-Za-z0-9._-"  # of sequence, setting and task names: they name folders
KEYS = ("sequences", "methods", "strides", "seeds", "settings", "tasks", "timeout_s")


@dataclass(frozen=True)
class SequenceSpec:
    name: str  # unique in the matrix: the cells' folder names and the table's rows
    source: str  # absolute path, or synthetic:...
    options: tuple[str, ...] = ()  # --format/--camera/--gt of the commands
    start: int | None = None
    end: int | None = None
    stride: int = 1  # --stride: every stride-th frame is played


@dataclass(frozen=True)
class TaskSpec:
    name: str  # unique in the matrix
    task: str  # one of TASKS
    args: tuple[str, ...] = ()  # more options of its command


@dataclass(frozen=True)
class Cell:
    sequence: SequenceSpec
    method: str
    setting: str
    overrides: tuple[str, ...]  # KEY=VALUE
    task: TaskSpec
    seed: int

    @property
    def key(self) -> str:
        """The cell's folder name: what resume recognizes a finished cell by."""
        return f"{self.sequence.name}__{self.method}__{self.setting}__{self.task.name}__seed{self.seed}"

    def labels(self) -> dict[str, Any]:
        return {"sequence": self.sequence.name, "method": self.method, "setting": self.setting,
                "task": self.task.name, "seed": self.seed}


@dataclass
class Matrix:
    sequences: list[SequenceSpec]
    methods: list[str]
    seeds: list[int] = field(default_factory=lambda: [0])
    settings: dict[str, tuple[str, ...]] = field(default_factory=lambda: {"default": ()})
    tasks: list[TaskSpec] = field(default_factory=lambda: [TaskSpec("run", "run")])
    timeout_s: float = DEFAULT_TIMEOUT_S

    def cells(self) -> list[Cell]:
        """Every cell, in the order of the table: task, setting, sequence, method, seed."""
        return [Cell(sequence, method, setting, overrides, task, seed)
                for task in self.tasks for setting, overrides in self.settings.items()
                for sequence in self.sequences for method in self.methods for seed in self.seeds]


def load_matrix(path: Path) -> Matrix:
    """The matrix in ``path``; InputError naming the file and the entry that is wrong."""
    try:
        document = yaml.safe_load(path.read_text())
    except OSError as error:
        raise InputError(f"{path}: cannot read the matrix ({error.strerror or error})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text file (the matrix is YAML)") from None
    except yaml.YAMLError as error:
        raise InputError(f"{path}: not valid YAML ({_one_line(error)})") from None
    return parse_matrix(document, str(path))


def parse_matrix(document: Any, origin: str) -> Matrix:
    if not isinstance(document, dict):
        raise InputError(f"{origin}: expected a mapping with the keys {', '.join(KEYS)}")
    unknown = sorted(set(document) - set(KEYS), key=str)
    if unknown:
        raise InputError(f"{origin}: unknown key {unknown[0]!r} (expected {', '.join(KEYS)})")
    for required in ("sequences", "methods"):
        if required not in document:
            raise InputError(f"{origin}: no '{required}' list")
    sequences = [_sequence(entry, f"{origin}: sequences[{i}]") for i, entry in enumerate(_list(document, "sequences",
                                                                                                origin))]
    sequences = _strided(sequences, _strides(_list(document, "strides", origin, [1]), origin))
    tasks = [_task(entry, f"{origin}: tasks[{i}]") for i, entry in enumerate(_list(document, "tasks", origin,
                                                                                     ["run"]))]
    _unique([sequence.name for sequence in sequences], f"{origin}: sequences")
    _unique([task.name for task in tasks], f"{origin}: tasks")
    cut = next((sequence for sequence in sequences if sequence.start is not None or sequence.end is not None), None)
    experiment = next((task for task in tasks if task.task != "run"), None)
    if cut is not None and experiment is not None:
        raise InputError(f"{origin}: sequence {cut.name} has a start or an end, which only the task run takes "
                         f"(not {experiment.task})")
    return Matrix(
        sequences=sequences,
        methods=_methods(_list(document, "methods", origin), origin),
        seeds=_seeds(_list(document, "seeds", origin, [0]), origin),
        settings=_settings(document.get("settings", {"default": {}}), origin),
        tasks=tasks,
        timeout_s=_positive(document.get("timeout_s", DEFAULT_TIMEOUT_S), f"{origin}: timeout_s"),
    )


def _list(document: dict, key: str, origin: str, default: list | None = None) -> list:
    value = document.get(key, default)
    if not isinstance(value, list) or not value:
        raise InputError(f"{origin}: '{key}' must be a non-empty list")
    return value


def _sequence(entry: Any, where: str) -> SequenceSpec:
    if isinstance(entry, str):
        entry = {"path": entry}
    if not isinstance(entry, dict) or not isinstance(entry.get("path"), str):
        raise InputError(f"{where}: expected a path, or a mapping with 'path' (and name, format, camera, gt, start, "
                         "end, stride)")
    unknown = sorted(set(entry) - {"path", "name", *SOURCE_OPTIONS, "start", "end", "stride"})
    if unknown:
        raise InputError(f"{where}: unknown key {unknown[0]!r}")
    source = _source(entry["path"])
    options: list[str] = []
    for key, option in SOURCE_OPTIONS.items():
        if key in entry:
            value = str(entry[key])
            options += [option, str(Path(value).absolute()) if key in PATH_OPTIONS else value]
    start, end = (_frame(entry.get(key), f"{where}: {key}") for key in ("start", "end"))
    stride = _stride(entry.get("stride", 1), f"{where}: stride")
    name = str(entry.get("name") or _name_of(entry["path"]))
    _check_name(name, where)
    return SequenceSpec(name, source, tuple(options), start, end, stride)


def _strides(values: list, origin: str) -> list[int]:
    strides = [_stride(value, f"{origin}: strides") for value in values]
    _unique(strides, f"{origin}: strides")
    return strides


def _stride(value: Any, where: str) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise InputError(f"{where}: expected a stride >= 1 (every how many frames one is played), got {value!r}")
    return value


def _strided(sequences: list[SequenceSpec], strides: list[int]) -> list[SequenceSpec]:
    """Each sequence at each stride of the matrix, a stride other than 1 named in the sequence's name (NAME.strideK)
    so that it is a row of the table of its own."""
    return [sequence if stride == 1 else replace(sequence, name=f"{sequence.name}.stride{sequence.stride * stride}",
                                                 stride=sequence.stride * stride)
            for sequence in sequences for stride in strides]


def _source(path: str) -> str:
    if path == BUNDLED:
        return str(DEFAULT_SEQUENCE)
    if path.startswith(SYNTHETIC_PREFIX):
        return path
    return str(Path(path).expanduser().absolute())


def _name_of(path: str) -> str:
    if path.startswith(SYNTHETIC_PREFIX):
        return re.sub(f"[^{NAME_CHARACTERS}]", "-", path)
    return Path(_source(path)).name


def _frame(value: Any, where: str) -> int | None:
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise InputError(f"{where}: expected a frame number >= 0, got {value!r}")
    return value


def _task(entry: Any, where: str) -> TaskSpec:
    if isinstance(entry, str):
        entry = {"task": entry}
    if not isinstance(entry, dict) or entry.get("task") not in TASKS:
        raise InputError(f"{where}: expected one of {', '.join(TASKS)}, or a mapping with 'task' (and name, args)")
    args = entry.get("args", [])
    if not isinstance(args, list):
        raise InputError(f"{where}: 'args' must be a list of options, e.g. [--at, '100']")
    name = str(entry.get("name", entry["task"]))
    _check_name(name, where)
    return TaskSpec(name, entry["task"], tuple(str(arg) for arg in args))


def _methods(values: list, origin: str) -> list[str]:
    for value in values:
        if value not in IMPLEMENTED_METHODS:
            raise InputError(f"{origin}: methods: unknown method {value!r} (available: "
                             f"{', '.join(IMPLEMENTED_METHODS)})")
    _unique(values, f"{origin}: methods")
    return [str(value) for value in values]


def _seeds(values: list, origin: str) -> list[int]:
    for value in values:
        if not isinstance(value, int) or isinstance(value, bool):
            raise InputError(f"{origin}: seeds: expected integers, got {value!r}")
    _unique(values, f"{origin}: seeds")
    return values


def _settings(value: Any, origin: str) -> dict[str, tuple[str, ...]]:
    """``{name: {key: value}}`` or ``{name: ["key=value", ...]}``: the --set overrides of each named setting."""
    if not isinstance(value, dict) or not value:
        raise InputError(f"{origin}: 'settings' must map names to overrides, e.g. {{coarse: "
                         "{direct.initializer: coarse}}")
    settings = {}
    for name, overrides in value.items():
        where = f"{origin}: settings.{name}"
        _check_name(str(name), where)
        if overrides is None:
            overrides = {}
        if isinstance(overrides, dict):
            settings[str(name)] = tuple(f"{key}={_yaml_value(item)}" for key, item in overrides.items())
        elif isinstance(overrides, list) and all(isinstance(item, str) and "=" in item for item in overrides):
            settings[str(name)] = tuple(overrides)
        else:
            raise InputError(f"{where}: expected a mapping of settings or a list of KEY=VALUE")
    return settings


def _yaml_value(value: Any) -> str:
    """A value as ``--set`` reads it back (YAML): true, 0.5, [1, 2], a string."""
    return value if isinstance(value, str) else yaml.safe_dump(value, default_flow_style=True).strip().removesuffix(
        "\n...").strip()


def _check_name(name: str, where: str) -> None:
    """Names become folder names (a cell's) and table rows: letters, digits, '.', '_' and '-' only."""
    if not re.fullmatch(f"[{NAME_CHARACTERS}]+", name):
        raise InputError(f"{where}: name {name!r} may only have letters, digits, '.', '_' and '-'")


def _positive(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
        raise InputError(f"{where}: expected a positive number of seconds, got {value!r}")
    return float(value)


def _unique(names: list, where: str) -> None:
    seen = set()
    for name in names:
        if name in seen:
            raise InputError(f"{where}: {name!r} appears twice")
        seen.add(name)


def _one_line(error: Exception) -> str:
    return " ".join(str(error).split())
