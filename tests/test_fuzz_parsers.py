"""Every parser of user input, fuzzed: any input gives either a valid result or the project's InputError (which the
CLI prints as one line with exit code 2), never another exception.

Inputs are drawn three ways: valid files with random edits (to reach deep into a parser), lines of tokens that
files of that kind are made of (numbers of every sort, keywords, separators), and raw bytes. The runs are
derandomized (the same examples every time) and short, so that the whole file takes a few seconds.
"""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from app.bench.cell import command
from app.bench.matrix import load_matrix
from app.cli import build_parser
from vo_core.config import load_config
from vo_core.datasets import open_sequence
from vo_core.datasets.calibration import load_camera_file
from vo_core.datasets.euroc import read_image_list as read_data_csv, read_sensor_yaml
from vo_core.datasets.tum_rgbd import read_image_list as read_rgb_txt
from vo_core.errors import InputError
from vo_core.features.vocabulary import Vocabulary
from vo_core.trajectory import read_trajectory

FUZZ = settings(max_examples=60, deadline=None, derandomize=True, database=None)
FEW = settings(FUZZ, max_examples=25)  # for the inputs that open a whole sequence

NUMBERS = st.one_of(
    st.integers(-10**20, 10**20).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["0", "1", "-1", "1e400", "-0.0", "nan", "inf", "1403715273262142976", "0x10", "1_000", ""]),
)
WORDS = st.sampled_from(["#", ",", ":", "Pinhole", "FOV", "RadTan", "EquiDistant", "KannalaBrandt", "crop", "full",
                         "none", "P0:", "P2:", "a.png", "rgb/1.png", "[", "]", "{", "}", "-", "null", "true"])
TOKENS = st.one_of(NUMBERS, NUMBERS, WORDS, st.text(max_size=4))


def lines(tokens=TOKENS, max_lines: int = 6) -> st.SearchStrategy[str]:
    line = st.tuples(st.lists(tokens, max_size=14), st.sampled_from([" ", ",", ", ", "\t"]))
    return st.lists(line.map(lambda pair: pair[1].join(pair[0])), max_size=max_lines).map("\n".join)


def edits_of(valid: str) -> st.SearchStrategy[str]:
    """``valid`` with a slice replaced by a few characters or tokens: mostly well-formed, wrong somewhere."""
    cut = st.integers(0, len(valid))
    return st.tuples(cut, cut, st.one_of(st.text(max_size=3), TOKENS)).map(
        lambda edit: valid[:min(edit[:2])] + edit[2] + valid[max(edit[:2]):])


def text_files(valid: str, tokens=TOKENS) -> st.SearchStrategy[bytes]:
    as_bytes = st.one_of(edits_of(valid), lines(tokens)).map(lambda text: text.encode("utf-8", "surrogatepass"))
    return st.one_of(as_bytes, as_bytes, st.binary(max_size=64))


YAML_KEYS = st.sampled_from(["model", "intrinsics", "distortion", "resolution", "T_BS", "data", "cols", "rows",
                             "camera_model", "distortion_model", "distortion_coefficients", "method", "seed",
                             "direct", "dataset", "tracker", "window", "read_ahead", "enabled"])
YAML_SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.floats(),
                         st.sampled_from(["pinhole", "radtan", "fov", "equidistant", "radial-tangential", "abc"]))
YAML_VALUES = st.recursive(YAML_SCALARS, lambda inner: st.lists(inner, max_size=17)
                           | st.dictionaries(YAML_KEYS, inner, max_size=5), max_leaves=24)


def yaml_files(valid: str) -> st.SearchStrategy[bytes]:
    documents = st.dictionaries(YAML_KEYS, YAML_VALUES, max_size=6).map(lambda d: yaml.safe_dump(d).encode())
    return st.one_of(documents, text_files(valid))


def parses_or_refuses(parse, *args):
    """``parse(*args)``, or None when it raises InputError; any other exception fails the test."""
    try:
        return parse(*args)
    except InputError:
        return None


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("fuzz")


# ------------------------------------------------------------------------------------------ calibration

CAMERA_YAML = "model: radtan\nintrinsics: [500.0, 501.0, 319.5, 239.5]\ndistortion: [0.1, -0.2, 0.001, 0.002]\n" \
              "resolution: [640, 480]\n"
DSO_CAMERA = "RadTan 0.5 0.6 0.5 0.5 0.1 -0.2 0.001 0.002\n640 480\ncrop\n320 240\n"
SENSOR_YAML = "%YAML:1.0\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n" \
              "resolution: [752, 480]\ncamera_model: pinhole\nintrinsics: [458.6, 457.3, 367.2, 248.4]\n" \
              "distortion_model: radial-tangential\ndistortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]\n"


@FUZZ
@given(content=yaml_files(CAMERA_YAML))
def test_camera_yaml(folder, content):
    (folder / "camera.yaml").write_bytes(content)
    parses_or_refuses(load_camera_file, folder / "camera.yaml")


@FUZZ
@given(content=text_files(DSO_CAMERA))
def test_dso_camera_txt(folder, content):
    (folder / "camera.txt").write_bytes(content)
    parses_or_refuses(load_camera_file, folder / "camera.txt")


FINITE_OR_NOT = st.one_of(st.floats(), st.sampled_from([0.0, -1.0, 1e-300, 1e300]))


@FEW
@given(model=st.sampled_from(["pinhole", "radtan", "equidistant", "fov"]),
       intrinsics=st.lists(FINITE_OR_NOT, min_size=4, max_size=4), distortion=st.lists(FINITE_OR_NOT, max_size=5),
       output=st.sampled_from(["crop", "full", "none"]))
def test_camera_numbers_that_parse_but_describe_no_camera(images, model, intrinsics, distortion, output):
    """A camera that parses goes on to the rectification: a distortion of 1e300 must not break it there."""
    camera = {"model": model, "intrinsics": intrinsics, "distortion": distortion, "resolution": [32, 24]}
    (images / "rgb" / "camera.yaml").write_text(yaml.safe_dump(camera))
    (images / "rgb" / "times.txt").unlink(missing_ok=True)
    sequence = parses_or_refuses(open_sequence, images / "rgb", None, None, output)
    if sequence is not None:
        assert sequence[0].image is not None


@FUZZ
@given(content=yaml_files(SENSOR_YAML))
def test_euroc_sensor_yaml(folder, content):
    (folder / "sensor.yaml").write_bytes(content)
    parses_or_refuses(read_sensor_yaml, folder / "sensor.yaml")


# ------------------------------------------------------------------------------------------ trajectories

TUM = "# timestamp tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n1.1 0.1 0 0 0 0 0.0998 0.995\n"
KITTI = "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0.5 0 1 0 0 0 0 1 1.5\n"
EUROC = "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n" \
        "1403715273262142976,0,0,0,1,0,0,0\n1403715273312142976,0.1,0,0,1,0,0,0\n"


@FUZZ
@given(content=st.one_of(text_files(TUM), text_files(KITTI), text_files(EUROC)),
       format=st.sampled_from([None, "tum", "kitti", "euroc"]))
def test_trajectory_files(folder, content, format):
    (folder / "trajectory.txt").write_bytes(content)
    parses_or_refuses(read_trajectory, folder / "trajectory.txt", format)


@FUZZ
@given(content=text_files("0.0\n0.1\n"))
def test_kitti_times_txt_beside_the_poses(folder, content):
    (folder / "kitti").mkdir(exist_ok=True)
    (folder / "kitti" / "poses.txt").write_text(KITTI)
    (folder / "kitti" / "times.txt").write_bytes(content)
    parses_or_refuses(read_trajectory, folder / "kitti" / "poses.txt", "kitti")


# ------------------------------------------------------------------------------------------ image lists


@pytest.fixture(scope="module")
def images(folder) -> Path:
    """Two small images, 1.png and 2.png, and a camera for them."""
    root = folder / "images"
    (root / "rgb").mkdir(parents=True)
    for name in ("1.png", "2.png"):
        cv2.imwrite(str(root / "rgb" / name), np.full((24, 32), 128, np.uint8))
    (root / "camera.yaml").write_text("model: pinhole\nintrinsics: [40, 40, 15.5, 11.5]\nresolution: [32, 24]\n")
    return root


@FUZZ
@given(content=text_files("# timestamp filename\n1.0 rgb/1.png\n1.1 rgb/2.png\n"))
def test_tum_rgb_txt(images, content):
    (images / "rgb.txt").write_bytes(content)
    parses_or_refuses(read_rgb_txt, images / "rgb.txt")


@FUZZ
@given(content=text_files("#timestamp [ns],filename\n1403715273262142976,1.png\n1403715273312142976,2.png\n"))
def test_euroc_data_csv(images, content):
    (images / "data").mkdir(exist_ok=True)
    for name in ("1.png", "2.png"):
        (images / "data" / name).write_bytes((images / "rgb" / name).read_bytes())
    (images / "data.csv").write_bytes(content)
    parses_or_refuses(read_data_csv, images / "data.csv")


@FEW
@given(content=text_files("1.0\n1.5\n"))
def test_image_folder_times_txt(images, content):
    (images / "rgb" / "times.txt").write_bytes(content)
    (images / "rgb" / "camera.yaml").write_text((images / "camera.yaml").read_text())
    parses_or_refuses(open_sequence, images / "rgb")


# ------------------------------------------------------------------------------------------ images

PNG = cv2.imencode(".png", np.arange(24 * 32, dtype=np.uint8).reshape(24, 32))[1].tobytes()
JPEG = cv2.imencode(".jpg", np.arange(24 * 32, dtype=np.uint8).reshape(24, 32))[1].tobytes()


def truncated(data: bytes) -> st.SearchStrategy[bytes]:
    return st.integers(0, len(data)).map(lambda length: data[:length])


@FEW
@given(first=st.one_of(truncated(PNG), truncated(JPEG), st.binary(max_size=64)),
       second=st.one_of(truncated(PNG), st.just(b"")), policy=st.sampled_from(["skip", "abort"]))
def test_truncated_empty_or_foreign_files_where_images_are_expected(folder, first, second, policy):
    root = folder / "bad_images"
    root.mkdir(exist_ok=True)
    (root / "camera.yaml").write_text("model: pinhole\nintrinsics: [40, 40, 15.5, 11.5]\nresolution: [32, 24]\n")
    (root / "0.png").write_bytes(PNG)
    (root / "1.png").write_bytes(first)
    (root / "2.jpg").write_bytes(second)
    sequence = parses_or_refuses(open_sequence, root, None, None, "crop", policy)
    frames = [] if sequence is None else parses_or_refuses(list, sequence) or []
    for frame in frames:
        assert (frame.image is None) == (frame.error is not None)
        assert frame.image is None or frame.image.shape == (24, 32)


# ------------------------------------------------------------------------------------------ configuration

CONFIG_YAML = "method: direct\nseed: 3\ndataset:\n  read_ahead: 4\ndirect:\n  tracker:\n    huber_threshold: 9\n"


@FUZZ
@given(content=yaml_files(CONFIG_YAML))
def test_config_yaml(folder, content):
    (folder / "config.yaml").write_bytes(content)
    parses_or_refuses(load_config, folder / "config.yaml")


SET_KEYS = st.sampled_from(["seed", "method", "direct.tracker.huber_threshold", "direct.tracker.max_iterations",
                            "direct.coarse_init.idepth_range", "direct.window.enabled", "dataset", "direct..x", "",
                            "dataset.undistort_output"])


@FUZZ
@given(key=st.one_of(SET_KEYS, st.text(max_size=8)), value=st.one_of(TOKENS, lines(max_lines=2), YAML_VALUES.map(
    lambda value: yaml.safe_dump(value, default_flow_style=True).strip())), equals=st.booleans())
def test_set_option(key, value, equals):
    parses_or_refuses(load_config, None, [f"{key}={value}" if equals else key + value])


@FUZZ
@given(text=st.one_of(lines(st.one_of(NUMBERS, st.just(":")), max_lines=1).map(lambda t: t.replace(" ", "")),
                      st.text(max_size=10)), option=st.sampled_from(["--drop", "--jump"]))
def test_drop_and_jump_options(text, option):
    """--drop FRAME:COUNT and --jump FRAME:TARGET."""
    args = parses_or_refuses(build_parser().parse_args, ["run", f"{option}={text}"])
    if args is not None:
        (frame, second), = args.drops or args.jumps
        assert frame >= 0 and (second >= 1 if option == "--drop" else second >= 0 and second != frame)


# ------------------------------------------------------------------------------------------ vocabulary

# A vocabulary of a root and three words (k 3, L 1), as Vocabulary.save writes it.
VOCABULARY_ARRAYS = {"format_version": np.int64(1), "kind": np.str_("fdmo-orb-vocabulary"), "branching": np.int64(3),
                     "depth": np.int64(1), "parents": np.array([-1, 0, 0, 0], np.int32),
                     "node_descriptors": np.arange(4 * 32, dtype=np.uint8).reshape(4, 32),
                     "word_weights": np.array([0.5, 1.0, 2.0])}
ARRAY_DTYPES = st.sampled_from([np.int8, np.int32, np.int64, np.uint8, np.uint64, np.float32, np.float64, np.bool_,
                                np.complex64, "<U3", "S2"])
NUMPY_VALUES = st.one_of(
    st.tuples(ARRAY_DTYPES, st.lists(st.integers(0, 5), max_size=2)).flatmap(
        lambda spec: arrays(spec[0], tuple(spec[1]))),
    st.sampled_from([np.int64(0), np.int64(-1), np.int64(10**18), np.float64(np.nan), np.str_("x"), np.bool_(True),
                     np.array([-1, 0, 1, 1, 2, 2], np.int64), np.array([0, 0, 0], np.uint64),
                     np.array([-1, 0, 0, 0], np.float64), np.zeros((4, 32), np.int8)]),
)


def vocabulary_files() -> st.SearchStrategy[bytes]:
    """npz files of the valid vocabulary with keys replaced by other arrays or left out, whole or truncated."""
    edits = st.dictionaries(st.sampled_from(sorted(VOCABULARY_ARRAYS)), st.one_of(NUMPY_VALUES, st.none()), max_size=3)

    def npz(changes: dict) -> bytes:
        values = {key: changes.get(key, value) for key, value in VOCABULARY_ARRAYS.items()}
        buffer = io.BytesIO()
        np.savez(buffer, **{key: value for key, value in values.items() if value is not None})
        return buffer.getvalue()

    files = edits.map(npz)
    return st.one_of(files, files, st.tuples(files, st.floats(0, 1)).map(lambda pair: pair[0][:int(len(pair[0]) * pair[1])]),
                     st.binary(max_size=64))


@FUZZ
@given(content=vocabulary_files())
def test_vocabulary_file(folder, content):
    (folder / "vocabulary.npz").write_bytes(content)
    vocabulary = parses_or_refuses(Vocabulary.load, folder / "vocabulary.npz")
    if vocabulary is not None:  # a file that loads describes a tree the descent can use
        vocabulary.transform(np.zeros((2, 32), np.uint8))


MATRIX = """sequences:
  - synthetic:smooth:30
  - {path: data/kitti, name: kitti, format: kitti, gt: gt.txt}
methods: [fdmo, klt]
seeds: [0, 1]
settings: {default: {}, coarse: {direct.initializer: coarse}}
tasks: [run, {task: frame-drop, name: drop, args: [--at, '10']}]
timeout_s: 60
"""
MATRIX_KEYS = st.sampled_from(["sequences", "methods", "seeds", "settings", "tasks", "timeout_s", "path", "name",
                               "format", "camera", "gt", "start", "end", "task", "args", "default", "run"])
MATRIX_VALUES = st.recursive(
    st.one_of(YAML_SCALARS, st.sampled_from(["fdmo", "klt", "run", "two-loop", "frame-drop", "bundled", "a/b",
                                             "synthetic:smooth", "x=1"])),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(MATRIX_KEYS, inner, max_size=4), max_leaves=20)


@FUZZ
@given(content=st.one_of(st.dictionaries(MATRIX_KEYS, MATRIX_VALUES, max_size=6).map(lambda d: yaml.safe_dump(d)
                                                                                    .encode()),
                         text_files(MATRIX)))
def test_bench_matrix(folder, content):
    """fdmo bench's matrix: a matrix whose every cell has a command line, or InputError."""
    path = folder / "matrix.yaml"
    path.write_bytes(content)
    matrix = parses_or_refuses(load_matrix, path)
    if matrix is not None:
        for cell in matrix.cells()[:50]:
            assert command(cell, folder / "cell")[:3][1:] == ["-m", "app"]

