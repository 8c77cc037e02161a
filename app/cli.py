"""The command line: ``fdmo run | eval | info | plot | vocabulary | experiment | bench``.

    fdmo run [SOURCE | camera:N --camera FILE] [--out DIR] [--method fdmo|direct|features|klt] [--config FILE]
             [--set key=value ...] [--start N] [--end N] [--drop FRAME:COUNT ...] [--jump FRAME:TARGET ...]
             [--gt FILE] [--realtime] [--mapping sync|threaded] [--rrd FILE] [--rrd-part-frames N | --no-rrd]
             [--viser [--host ADDRESS] [--port P]] [--quiet]
    fdmo eval EST GT [--align sim3|se3|none] [--json]
    fdmo info SOURCE [--json]
    fdmo vocabulary train IMAGE... --out FILE [--branching K] [--depth L] [--seed S]
    fdmo plot RESULT_DIR [--out FILE] [--gt FILE] [--align sim3|se3|none] [--plane xy|xz|yz]
    fdmo experiment frame-drop|two-loop|timing SOURCE [--methods fdmo,direct,klt] [--out DIR] ...
    fdmo bench MATRIX.yaml [--workers N] [--ray auto|ADDRESS] [--out DIR] [--retry-failed]

Exit code 0 on success, 2 with a one-line message on bad input (never a traceback), 130 when interrupted by Ctrl-C
(SIGINT) and 143 by SIGTERM, 141 when the reader of the output went away (``fdmo info X | head``): app/exit_codes.py.
The viewers and matplotlib are imported only when asked for, so a headless run never loads viser.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence as SequenceOf
from pathlib import Path
from typing import Any, NoReturn

from app.exit_codes import EXIT_BAD_INPUT, EXIT_BROKEN_PIPE, EXIT_INTERRUPTED, EXIT_OK, exit_code_of_signal
from app.kernel_build import kernel_builds_announced
from app.player import REAL_TIME
from app.plot import DEFAULT_PLOT_FILE, PLANES
from app.process_start import MAPPING_MODES, mapping_mode
from app.sinks.background import BackgroundSink
from app.sinks.recording_parts import PART_FRAMES, opening_argument, recording_files
from vo_core.config import METHODS, Config, load_config
from vo_core.datasets import DEFAULT_SEQUENCE, LAYOUTS
from vo_core.errors import InputError
from vo_core.eval import ALIGNMENTS, DEFAULT_MAX_DT_S
from vo_core.events import EventKind
from vo_core.features.config import VocabularyConfig

DEFAULT_RESULTS_ROOT = Path("results")
MIN_BUILD_REPORTED_S = 1.0  # a kernel built in less (a new signature) is not worth a summary line
DEFAULT_RECORDING = "recording.rrd"
DEFAULT_VISER_HOST = "127.0.0.1"  # this machine only: the page controls the run
DEFAULT_VISER_PORT = 8080
# Read when rerun's library loads: its allocator (mimalloc) gives freed memory back at once rather than keeping it
# for later, and commits its arenas as they fill (issue 17: 13-16 MB less on teddy).
RECORDING_ALLOCATOR = {"MIMALLOC_PURGE_DELAY": "0", "MIMALLOC_ARENA_EAGER_COMMIT": "0"}


class _OneLineParser(argparse.ArgumentParser):
    """argparse, but a usage error is one line on stderr and exit code 2 (the CLI contract), with one prefix
    (``fdmo: error: ``, main's): where an option's own check names the option (``--drop 10: ...``), argparse's
    ``argument --drop: `` before it goes."""

    def error(self, message: str) -> NoReturn:
        option, separator, rest = message.removeprefix("argument ").partition(": ")
        if message.startswith("argument ") and separator and rest.startswith(f"{option.split('/')[-1]} "):
            message = rest
        raise InputError(f"{message} (see {self.prog} --help)")


def _drop(text: str) -> tuple[int, int]:
    """``FRAME:COUNT`` of --drop."""
    frame, count = _two_integers("--drop", text, "FRAME:COUNT")
    if frame < 0 or count < 1:
        raise argparse.ArgumentTypeError(f"--drop {text}: FRAME must be >= 0 and COUNT >= 1")
    return frame, count


def _jump(text: str) -> tuple[int, int]:
    """``FRAME:TARGET`` of --jump."""
    frame, target = _two_integers("--jump", text, "FRAME:TARGET")
    if frame < 0 or target < 0 or target == frame:
        raise argparse.ArgumentTypeError(f"--jump {text}: FRAME and TARGET must be >= 0 and differ")
    return frame, target


def _two_integers(option: str, text: str, form: str) -> tuple[int, int]:
    first, _, second = text.partition(":")
    try:
        return int(first), int(second)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{option} {text}: expected {form}, two integers") from None


def _stride(text: str) -> int:
    """``K`` of --stride."""
    return _integer_within("--stride", text, 1)


def _port(text: str) -> int:
    return _integer_within("--port", text, 1, 65535)


def _part_frames(text: str) -> int:
    """``N`` of --rrd-part-frames: 0 is one file."""
    return _integer_within("--rrd-part-frames", text, 0)


def _integer_within(option: str, text: str, lowest: int, highest: int | None = None) -> int:
    """An integer option's value, from ``lowest`` to ``highest`` (no upper bound where None)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{option} {text}: expected an integer") from None
    if value < lowest or (highest is not None and value > highest):
        bounds = f"{lowest} or more" if highest is None else f"between {lowest} and {highest}"
        raise argparse.ArgumentTypeError(f"{option} {text}: must be {bounds}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = _OneLineParser(prog="fdmo", description="FDMO: feature assisted direct monocular odometry")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_OneLineParser)

    run = commands.add_parser("run", help="run the odometry over a sequence and write the result files")
    run.add_argument("source", nargs="?",
                     help="dataset folder or video, synthetic:PRESET[:FRAMES[:WIDTHxHEIGHT]] (vo_core.synthetic), or "
                          "camera:N (a live camera, with --camera FILE); default: the bundled sequence")
    run.add_argument("--out", type=Path, help="results folder (default: results/<sequence>_<time>/)")
    run.add_argument("--method", choices=METHODS, help=f"overrides the configuration's method (default: {Config.method})")
    run.add_argument("--config", type=Path, help="YAML configuration (the format of config.yaml)")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override one setting, e.g. --set direct.tracker.huber_threshold=9 (repeatable)")
    run.add_argument("--loop-closure", action="store_true",
                     help="close loops over the feature map (fdmo: FDMO as SLAM; off: the paper's odometry)")
    run.add_argument("--start", type=int, help="first frame (position in the sequence)")
    run.add_argument("--end", type=int, help="stop before this frame")
    run.add_argument("--drop", dest="drops", type=_drop, action="append", default=[], metavar="FRAME:COUNT",
                     help="the odometry never sees frames FRAME..FRAME+COUNT-1 (repeatable)")
    run.add_argument("--jump", dest="jumps", type=_jump, action="append", default=[], metavar="FRAME:TARGET",
                     help="after frame FRAME, go on from frame TARGET: back (frames played again) or ahead; "
                          "once per run (repeatable)")
    run.add_argument("--realtime", action="store_true",
                     help="frames arrive at their timestamps, as from a camera; those that arrive while the odometry "
                          "is busy are skipped (and counted), as a live system skips them")
    run.add_argument("--mapping", choices=MAPPING_MODES,
                     help="keyframe mapping on the tracking thread (sync: deterministic, the default) or on its own "
                          "thread (threaded: the default with --realtime and --viser)")
    recording = run.add_mutually_exclusive_group()
    recording.add_argument("--rrd", type=Path, help=f"Rerun recording file (default: <out>/{DEFAULT_RECORDING})")
    recording.add_argument("--no-rrd", action="store_true", help="write no Rerun recording")
    run.add_argument("--rrd-part-frames", type=_part_frames, metavar="N",
                     help=f"the recording goes on in a new file (FILE.part2.rrd, ...) every N frames, which bounds the "
                          f"memory the rerun SDK holds for the file; 0: one file (default: {PART_FRAMES})")
    run.add_argument("--viser", action="store_true", help="live browser view; stays up until Ctrl-C")
    run.add_argument("--host", default=DEFAULT_VISER_HOST,
                     help="address the viser page listens on (default: %(default)s, this machine only; "
                          "0.0.0.0 for every network interface)")
    run.add_argument("--port", type=_port, default=DEFAULT_VISER_PORT,
                     help="port of the viser page (default: %(default)s)")
    run.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    _add_source_options(run)

    evaluate = commands.add_parser("eval", help="metrics of an estimated trajectory against ground truth")
    evaluate.add_argument("estimate", type=Path, help="trajectory file (TUM, KITTI or EuRoC CSV)")
    evaluate.add_argument("ground_truth", type=Path, help="trajectory file (TUM, KITTI or EuRoC CSV)")
    evaluate.add_argument("--align", choices=ALIGNMENTS, default="sim3", help="alignment before the errors")
    evaluate.add_argument("--max-dt", type=float, default=DEFAULT_MAX_DT_S,
                          help="largest timestamp difference of an associated pair, seconds (TUM's associate.py)")
    evaluate.add_argument("--json", action="store_true", help="print JSON")

    info = commands.add_parser("info", help="what the loader finds in a dataset folder or video")
    info.add_argument("source", help="dataset folder or video, or synthetic:PRESET[:FRAMES[:WIDTHxHEIGHT]]")
    info.add_argument("--json", action="store_true", help="print JSON")
    _add_source_options(info)

    plot = commands.add_parser("plot", help="draw a run against its ground truth (PNG)")
    plot.add_argument("result_dir", type=Path, metavar="RESULT_DIR", help="a results folder of fdmo run")
    plot.add_argument("--out", type=Path, help="PNG file (default: <RESULT_DIR>/plot.png)")
    plot.add_argument("--gt", type=Path, metavar="FILE", help="ground truth (default: the run's groundtruth.tum)")
    plot.add_argument("--align", choices=ALIGNMENTS, default="sim3", help="alignment before the errors")
    plot.add_argument("--plane", choices=PLANES, help="plane of the top view (default: the ground truth's widest)")

    vocabulary = commands.add_parser("vocabulary", help="the bag-of-words vocabulary of the feature map")
    vocabulary_commands = vocabulary.add_subparsers(dest="vocabulary_command", required=True,
                                                    parser_class=_OneLineParser)
    train = vocabulary_commands.add_parser("train", help="train a vocabulary on the ORB features of images")
    train.add_argument("images", nargs="+", type=Path, metavar="IMAGE",
                       help="image files (a folder: every image in it, sorted)")
    train.add_argument("--out", type=Path, required=True, help="vocabulary file to write (.npz)")
    train.add_argument("--branching", type=int, default=VocabularyConfig.branching, help="k (default: %(default)s)")
    train.add_argument("--depth", type=int, default=VocabularyConfig.depth, help="L (default: %(default)s)")
    train.add_argument("--seed", type=int, default=0, help="seed of the k-means++ choices (default: %(default)s)")

    from app.experiments import add_experiment_parsers

    experiment = commands.add_parser("experiment", help="the experiments of FDMO section 5: frame-drop, two-loop, "
                                                        "timing")
    add_experiment_parsers(experiment, _OneLineParser, _add_source_options)

    from app.bench import add_arguments as add_bench_arguments

    bench = commands.add_parser("bench", help="a matrix of sequences x methods x settings x seeds, each cell a "
                                              "process, on this machine or a Ray cluster, gathered in one table")
    add_bench_arguments(bench)
    return parser


def _add_source_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--stride", type=_stride, default=1, metavar="K",
                        help="play every K-th frame, at its own timestamp: the camera at 1/K of its frame rate")
    parser.add_argument("--format", dest="layout", choices=LAYOUTS, help="force the dataset layout (default: detected)")
    parser.add_argument("--camera", type=Path, help="camera YAML or DSO camera.txt: replaces the dataset's calibration")
    parser.add_argument("--gt", type=Path, metavar="FILE",
                        help="ground truth (TUM, KITTI with a line per image, or EuRoC CSV; camera-to-world poses): "
                             "replaces the dataset's, for the evaluation and the viewers")


# ------------------------------------------------------------------------------------------------ run


def command_run(args: argparse.Namespace) -> int:
    code = _run_command(args)
    if args.own_process:
        _end_process(code)
    return code


def _end_process(code: int) -> NoReturn:
    """After a run in a process of its own: its files are written and closed, the recording flushed, the mapping
    threads and the feature half's process joined. What is left is the interpreter's teardown, freeing the maps and
    the compiled kernels object by object (0.2 s of a 9 s teddy run, 0.26 s with a recording), which nothing needs:
    the process ends here."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _run_command(args: argparse.Namespace) -> int:
    with kernel_builds_announced(None if args.quiet else _announce_kernel_build):
        return _run_source(args)


def _run_source(args: argparse.Namespace) -> int:
    from app.live import LiveCamera, LivePlayer, live_device, live_undistorter
    from app.pipeline import check_method, open_source
    from app.player import Player

    if args.no_rrd and args.rrd_part_frames is not None:
        raise InputError("--rrd-part-frames cannot be used with --no-rrd")
    device = None if args.source is None else live_device(args.source)
    if device is not None:
        _check_live_options(args)
        args.realtime = True  # a camera delivers its frames whether or not the odometry is ready for them
    config = run_config(args)
    if device is not None:
        undistorter = live_undistorter(device, args.camera, config.dataset.undistort_output)
        check_method(config, undistorter.camera)
        _warm_up(config, undistorter.camera, args.quiet)
        with contextlib.closing(LiveCamera(device, undistorter)) as camera:
            print(f"fdmo: live from {args.source} ({camera.camera.width}x{camera.camera.height} rectified); Ctrl-C "
                  "ends the run", file=sys.stderr)
            return _run_and_report(args, config, camera, LivePlayer(camera), show_progress=False)
    source = DEFAULT_SEQUENCE if args.source is None else args.source
    sequence = open_source(source, config.dataset, args.layout, args.camera, args.start, args.end, args.gt,
                           args.stride)
    check_method(config, sequence.camera)
    _check_drops_and_jumps(args.drops, args.jumps, sequence.indices)
    if args.realtime:
        _warm_up(config, sequence.camera, args.quiet)
    player = Player(sequence, args.drops, args.jumps, realtime=args.realtime)
    return _run_and_report(args, config, sequence, player, show_progress=not args.quiet)


def _announce_kernel_build() -> None:
    """Said once, when the process starts building compiled kernels (the first run on this machine): otherwise the
    first frames seem to hang for a minute or more."""
    from vo_core.kernel_cache import CACHE_VARIABLE

    clear = "\r\033[K" if sys.stderr.isatty() else ""  # the progress bar's line
    print(f"{clear}fdmo: building the compiled kernels, once for this installation (a minute or two; cached in "
          f"{os.environ[CACHE_VARIABLE]}: later runs start at once)", file=sys.stderr, flush=True)


def run_config(args: argparse.Namespace) -> Config:
    """The configuration of ``fdmo run``: the file's (or the defaults), then what the options change, then the user's
    own --set, then --method."""
    overrides = [*_live_overrides(args), *(["features.loop_closing.enabled=true"] if args.loop_closure else []),
                 *args.overrides, *([f"method={args.method}"] if args.method else [])]
    return load_config(args.config, overrides)


def _check_live_options(args: argparse.Namespace) -> None:
    """What a live camera cannot do: it has no frames to cut, drop or jump to, no layout and no ground truth, and
    the page's playback controls are for recorded sequences."""
    given = {"--start": args.start, "--end": args.end, "--stride": args.stride if args.stride != 1 else None,
             "--drop": args.drops, "--jump": args.jumps,
             "--format": args.layout, "--gt": args.gt, "--viser": args.viser}
    refused = [option for option, value in given.items() if value not in (None, [], False)]
    if refused:
        raise InputError(f"{args.source}: {', '.join(refused)} cannot be used with a live camera")


def _run_and_report(args: argparse.Namespace, config: Config, sequence, player, show_progress: bool) -> int:
    from app.pipeline import INTERRUPTED, run_sequence

    out_dir = args.out or _default_out_dir(sequence.name)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir}: exists and is not a folder")
    sinks = _sinks(args, sequence, player, out_dir)  # run_sequence closes them
    signals: list[int] = []
    try:
        summary = _until_signalled(player, signals, lambda: run_sequence(
            sequence, config, out_dir, sinks, player=player, show_progress=show_progress, keep_alive=args.viser))
    finally:
        if args.out is None and out_dir.is_dir():
            _link_latest(out_dir)
    if summary is not None and not args.quiet:
        recording = [] if args.no_rrd else recording_files(args.rrd or out_dir / DEFAULT_RECORDING)
        print(_summary_text(summary.metrics, out_dir, recording))
    if summary is None or summary.status == INTERRUPTED:
        # Cut short (the files are still valid): the exit code says so, as metrics.json does.
        print(f"fdmo: interrupted; results in {out_dir}", file=sys.stderr)
        return exit_code_of_signal(signals[0]) if signals else EXIT_INTERRUPTED
    if signals:  # --viser: the sequence was over and the page up; Ctrl-C is the way to quit
        print(f"fdmo: stopped; results in {out_dir}", file=sys.stderr)
    return EXIT_OK


def _live_overrides(args: argparse.Namespace) -> list[str]:
    """--mapping, and what live input changes, as settings (the user's own --set come after, and win). Live input
    maps on its own thread and does not wait for keyframes (DSO's real-time mode), nor for DSO's rotation guesses
    (direct.tracker.rotation_hypotheses), nor for the new start's epipolar witness (it runs beside mapping); a run
    with the page open maps on its own thread."""
    mode = mapping_mode(args.mapping, args.realtime, args.viser)
    overrides = [f"mapping.threaded={str(mode == 'threaded').lower()}"]
    live = ["mapping.wait_for_keyframes=false", "direct.tracker.rotation_hypotheses=false",
            "direct.start_check.epipolar.beside_mapping=true"]
    return overrides + (live if args.realtime else [])


def _warm_up(config: Config, camera, quiet: bool) -> None:
    """Before a real-time run's camera starts: the first-use costs (seconds) would otherwise skip its first
    frames (app.pipeline.warm_up)."""
    from app.pipeline import warm_up

    if not quiet:
        print("fdmo: getting ready (a short synthetic run loads the compiled kernels) before the camera starts",
              file=sys.stderr)
    seconds = warm_up(config, camera)
    if not quiet:
        print(f"fdmo: ready after {seconds:.1f} s", file=sys.stderr)


def _sinks(args: argparse.Namespace, sequence, player, out_dir: Path) -> list:
    sinks = []
    if not args.no_rrd:
        part_frames = PART_FRAMES if args.rrd_part_frames is None else args.rrd_part_frames
        sinks.append(_rerun_sink(args.rrd or out_dir / DEFAULT_RECORDING, sequence, args.own_process, part_frames))
    if args.viser:
        sinks.append(_viser_view(sequence, player, args.host, args.port))
    return sinks


def _check_drops_and_jumps(drops: list[tuple[int, int]], jumps: list[tuple[int, int]], frame_indices) -> None:
    """A drop or a jump at a frame the run never reaches, or a jump to a frame it does not have, is a typo, not an
    experiment: say so."""
    played = set(frame_indices.tolist())
    frames = f"({frame_indices[0]}..{frame_indices[-1]})"
    for option, pairs in (("--drop", drops), ("--jump", jumps)):
        for frame, second in pairs:
            if frame not in played:
                raise InputError(f"{option} {frame}:{second}: frame {frame} is not among the frames played {frames}")
    for frame, target in jumps:
        if target not in played:
            raise InputError(f"--jump {frame}:{target}: frame {target} is not in the sequence played {frames}")


@contextlib.contextmanager
def _signals_end_the_run(player, signals: list[int]) -> Iterator[None]:
    """Ctrl-C (SIGINT) and SIGTERM (a timeout, a job scheduler) end the run between two frames: the frame being
    tracked finishes, then the result files. The handler only tells the player (and appends the signal's number to
    ``signals``, for the exit code); raising KeyboardInterrupt instead would often land inside a compiled kernel,
    where numba turns it into a SystemError. A second signal stops at once (a frame can take long: the first run
    compiles the kernels)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may set signal handlers
        return

    def handle(signum, frame):
        signals.append(signum)
        if player.interrupted:
            raise KeyboardInterrupt
        player.interrupt()

    previous = {number: signal.signal(number, handle) for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _until_signalled(player, signals: list[int], run):
    """``run()``'s summary, or None when a second signal stopped the run mid-frame (its files are finished all
    the same: the pipeline writes them in a ``finally``); the signals received are appended to ``signals``."""
    try:
        with _signals_end_the_run(player, signals):
            return run()
    except (KeyboardInterrupt, SystemError) as error:
        # Raised inside a numba kernel, a KeyboardInterrupt surfaces as a SystemError caused by it.
        if isinstance(error, KeyboardInterrupt) or isinstance(error.__cause__, KeyboardInterrupt):
            return None
        raise


def _default_out_dir(sequence_name: str) -> Path:
    return DEFAULT_RESULTS_ROOT / f"{sequence_name}_{time.strftime('%Y%m%d-%H%M%S')}"


def _link_latest(out_dir: Path) -> None:
    """results/latest points at the newest default results folder."""
    latest = out_dir.parent / "latest"
    if latest.is_symlink() or not latest.exists():
        latest.unlink(missing_ok=True)
        latest.symlink_to(out_dir.name, target_is_directory=True)


def prepare_recording_process() -> None:
    """What a process of fdmo's own does before it loads rerun to record (issue 17): the allocator's settings
    (``RECORDING_ALLOCATOR``, which the user's environment overrides) and a pyarrow without pandas."""
    for name, value in RECORDING_ALLOCATOR.items():
        os.environ.setdefault(name, value)
    from app.sinks.rerun_sink import keep_pandas_unloaded

    keep_pandas_unloaded()


def _rerun_sink(path: Path, sequence, own_process: bool, part_frames: int):
    if own_process:
        prepare_recording_process()
    from app.sinks.rerun_sink import RerunSink  # imported here: a run without a recording never loads rerun

    path.parent.mkdir(parents=True, exist_ok=True)
    return BackgroundSink(RerunSink(path, sequence.camera, ground_truth=sequence.ground_truth,
                                    recording_name=_played(sequence), part_frames=part_frames))


def _viser_view(sequence, player, host: str, port: int):
    from app.sinks.viser_view import ViserView  # imported here: a headless run never loads viser

    player.speed = REAL_TIME  # watched live: at the sequence's own frame rate (the page's slider changes it)
    view = ViserView(sequence.camera, player, ground_truth=sequence.ground_truth, host=host, port=port,
                     wait_for_browser=True, title=f"FDMO: {_played(sequence)}")
    print(f"fdmo: live view at {view.url}; playback starts when a browser opens it (Ctrl-C to quit)",
          file=sys.stderr)
    return view


def _played(sequence) -> str:
    return played_name(sequence.name, getattr(sequence, "stride", 1))  # a live camera has no stride


def played_name(sequence_name: str, stride: int) -> str:
    """What was played, as the summary and the viewers name it: the sequence, and its stride where frames were left
    out."""
    return sequence_name if stride == 1 else f"{sequence_name} (every {stride} frames)"


def _summary_text(metrics: dict[str, Any], out_dir: Path, recording: SequenceOf[Path] = ()) -> str:
    """The summary printed at the end of a run; ``recording``: the files of its Rerun recording."""
    initialized = metrics["initialization_frame"]
    lines = [
        f"{played_name(metrics['sequence'], metrics['stride'])} ({metrics['method']}, {metrics['status']}): "
        f"tracked {metrics['tracked_frames']}/{metrics['processed_frames']} frames, "
        f"{'never initialized' if initialized is None else f'initialized at frame {initialized}'}, "
        f"{_counted(metrics['keyframes'], 'keyframe', 'keyframes')}, {metrics['fps'] or 0.0:.1f} fps",
    ]
    incidents = _incidents(metrics)
    if incidents:
        lines.append("  " + ", ".join(incidents))
    if metrics.get("kernel_build_s", 0.0) >= MIN_BUILD_REPORTED_S:
        lines.append(f"  the compiled kernels were built in {metrics['kernel_build_s']:.0f} s, once (not counted in "
                     "the fps)")
    evaluation = metrics.get("evaluation")
    if evaluation:
        lines.append("  " + _evaluation_line(evaluation))
    if len(recording) > 1:
        lines.append(f"  the recording is in {len(recording)} files: rerun {opening_argument(recording)} opens them "
                     "as one")
    if recording and not _has_display():
        # `rerun FILE` opens a window: without a display it fails (winit's EventLoopError).
        lines.append(f"  no display here: rerun --serve-web {opening_argument(recording)} shows the recording in a "
                     "browser")
    lines.append(f"  results in {out_dir}")  # last, as scripts read it
    return "\n".join(lines)


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _incidents(metrics: dict[str, Any]) -> list[str]:
    """What befell the run, each kind that happened with its count: frames it did not see, failures, recoveries."""
    events = Counter(metrics["events"])
    recovered, unrecovered = events[EventKind.RECOVERY_SUCCEEDED.value], events[EventKind.RECOVERY_FAILED.value]
    outcome = f"({recovered} succeeded, {unrecovered} failed)"
    counts = [
        (metrics["skipped_frames"], "unreadable frame skipped", "unreadable frames skipped"),
        (metrics["dropped_frames"], "frame dropped", "frames dropped"),
        (metrics["late_frames"], "frame skipped in real time (it arrived while the odometry was busy)",
         "frames skipped in real time (they arrived while the odometry was busy)"),
        (len(metrics["jumps"]), f"jump ({_jumps(metrics['jumps'])})", f"jumps ({_jumps(metrics['jumps'])})"),
        (events[EventKind.TRACKING_FAILED.value], "tracking failure", "tracking failures"),
        (events[EventKind.DIVERGENCE_DETECTED.value], "divergence", "divergences"),
        (recovered + unrecovered, f"recovery {outcome}", f"recoveries {outcome}"),
        (events[EventKind.REINITIALIZATION.value], "reinitialization", "reinitializations"),
        (events[EventKind.REINITIALIZATION_ABANDONED.value], "reinitialization abandoned (the old map came back)",
         "reinitializations abandoned (the old map came back)"),
        (events[EventKind.LOOP_CLOSED.value], "loop closed", "loops closed"),
        (events[EventKind.MAPS_MERGED.value], "map merged into the final one", "maps merged into the final one"),
    ]
    return [_counted(count, one, many) for count, one, many in counts if count]


def _jumps(jumps: list[dict[str, Any]]) -> str:
    return ", ".join(f"{jump['from_frame']} -> {jump['to_frame']}" for jump in jumps)


def _counted(count: int, one: str, many: str) -> str:
    return f"{count} {one if count == 1 else many}"


def _evaluation_line(evaluation: dict[str, Any]) -> str:
    if "error" in evaluation:
        return f"no evaluation: {evaluation['error']}"
    ate = evaluation["ate"]
    return f"ATE rmse {ate['rmse']:.4f} m over {evaluation['matched_poses']} poses (aligned: {evaluation['align']})"


# ----------------------------------------------------------------------------------------- eval, info


def command_eval(args: argparse.Namespace) -> int:
    from vo_core.eval import evaluate
    from vo_core.trajectory import read_trajectory

    estimate, ground_truth = read_trajectory(args.estimate), read_trajectory(args.ground_truth)
    result = evaluate(estimate, ground_truth, align=args.align, max_dt=args.max_dt)
    print(json.dumps(result, indent=2) if args.json else _as_text(result))
    return EXIT_OK


def command_info(args: argparse.Namespace) -> int:
    from app.pipeline import open_source
    from vo_core.config import DatasetConfig

    sequence = open_source(args.source, DatasetConfig(), layout=args.layout, camera_file=args.camera,
                           ground_truth_file=args.gt, stride=args.stride)
    description = sequence.describe()
    print(json.dumps(description, indent=2) if args.json else _as_text(description))
    return EXIT_OK


def command_plot(args: argparse.Namespace) -> int:
    from app.plot import plot_run

    out = args.out or args.result_dir / DEFAULT_PLOT_FILE
    print(plot_run(args.result_dir, out, args.gt, args.align, args.plane))
    print(f"wrote {out}")
    return EXIT_OK


def _as_text(values: dict[str, Any], indent: str = "") -> str:
    """A nested dict as indented ``key: value`` lines."""
    lines = []
    for key, value in values.items():
        if isinstance(value, dict):
            lines.append(f"{indent}{key}:")
            lines.append(_as_text(value, indent + "  "))
        else:
            lines.append(f"{indent}{key}: {_short(value)}")
    return "\n".join(line for line in lines if line)


def _short(value: Any) -> str:
    if isinstance(value, float):
        if value != 0.0 and abs(value) < 1e-3:
            return f"{value:.3e}"
        # Fixed point keeps timestamps whole (1341840000.123456, not 1.34184e+09); trailing zeros go.
        return f"{value:.6f}".rstrip("0").rstrip(".")
    if isinstance(value, list):
        return "[" + ", ".join(_short(v) for v in value) + "]"
    return str(value)


def command_vocabulary(args: argparse.Namespace) -> int:
    """``fdmo vocabulary train IMAGES... --out FILE``: then ``--set features.vocabulary.path=FILE`` uses it."""
    from vo_core.features.vocabulary import train_vocabulary_from_images

    if args.branching < 2 or args.depth < 1:
        raise InputError(f"a vocabulary needs --branching >= 2 and --depth >= 1, not {args.branching} and {args.depth}")
    paths = [path for given in args.images for path in _image_files(given)]
    config = VocabularyConfig(branching=args.branching, depth=args.depth)
    vocabulary = train_vocabulary_from_images(paths, config, seed=args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    vocabulary.save(args.out)
    print(f"wrote {args.out}: {vocabulary.num_words} words (k {args.branching}, L {args.depth}) from {len(paths)} "
          f"images")
    return EXIT_OK


def _image_files(path: Path) -> list[Path]:
    from vo_core.datasets.image_folder import image_files

    if path.is_dir():
        found = image_files(path)
        if not found:
            raise InputError(f"{path}: no images in this folder")
        return found
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    return [path]


def command_experiment(args: argparse.Namespace) -> int:
    """``fdmo experiment NAME SOURCE``: app/experiments/ writes the folder and prints the table."""
    from app.experiments import run_experiment

    run_experiment(args)
    return EXIT_OK


def command_bench(args: argparse.Namespace) -> int:
    """``fdmo bench MATRIX.yaml``: app/bench/ runs the cells and writes the table."""
    from app.bench import command_bench as run_bench

    return run_bench(args)


# ------------------------------------------------------------------------------------------------ main

COMMANDS = {"run": command_run, "eval": command_eval, "info": command_info, "plot": command_plot,
            "vocabulary": command_vocabulary, "experiment": command_experiment, "bench": command_bench}


def command_line() -> int:
    """The ``fdmo`` command and ``python -m app`` (both through app/__main__.py): ``main`` in a process of its own."""
    return main(own_process=True)


def main(argv: SequenceOf[str] | None = None, *, own_process: bool = False) -> int:
    """Runs a command line. ``own_process``: the process is fdmo's alone, so that its pyarrow serves the recording
    alone (``keep_pandas_unloaded``); not so where fdmo is called from other code (tests, scripts)."""
    try:
        args = build_parser().parse_args(argv)
        args.own_process = own_process
        return COMMANDS[args.command](args)
    except InputError as error:
        print(f"fdmo: error: {_one_line(str(error))}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:  # outside a run's frames (opening a video, building the odometry): nothing to finish
        print("fdmo: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # The reader of the output went away (`fdmo info X | head`): no error of ours. stdout now points nowhere,
        # or the interpreter's last flush of it would fail again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


def _one_line(message: str) -> str:
    return " ".join(message.split())


if __name__ == "__main__":
    sys.exit(main())
