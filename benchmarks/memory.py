"""Where a run's memory goes (issue 17): the libraries' floor, then a whole run broken down at its peak.

    python3 benchmarks/memory.py ../shared/data/tum_fr3_teddy_first200            # with the Rerun recording
    python3 benchmarks/memory.py ../shared/data/tum_fr3_teddy_first200 --no-rrd

1. The floor: a fresh interpreter imports what ``fdmo run`` imports, stage by stage, and reports its resident set
   (RSS, split into anonymous memory and the pages of mapped files: the libraries' code and data) after each:
   numpy, OpenCV, the scipy modules the project uses, numba, the project, the first compiled kernel loaded from
   numba's cache (numba then builds its runtime with LLVM), rerun (with the settings ``fdmo run`` gives it) and
   a first recorded entity. Where pandas is installed, fdmo run keeps pyarrow from loading it (45 MB).
2. The run: ``fdmo run FOLDER --quiet`` as a user starts it, its ``/proc/PID/smaps`` read every 0.2 s. At the
   sample with the largest RSS the memory is grouped by mapping: the heap, anonymous mappings (numpy's large
   arrays, the threads' arenas, the Rust allocator of rerun) and each library's pages. The peak RSS is the
   kernel's (os.wait4), which a 0.2 s sampling can miss by a little.
"""

from __future__ import annotations

import argparse
import collections
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.run_shared import markdown_table  # noqa: E402

MB = 1024 * 1024
SAMPLE_PERIOD_S = 0.2
TOP_GROUPS = 14

# Each stage runs in the same fresh interpreter after the ones above it.
FLOOR_STAGES = (
    ("interpreter", ""),
    ("numpy", "import numpy"),
    ("OpenCV", "import cv2"),
    ("scipy (spatial, sparse, linalg, transform)",
     "import scipy.spatial, scipy.sparse, scipy.linalg, scipy.spatial.transform"),
    ("numba", "import numba"),
    ("the project (app.pipeline, app.cli)", "import app.pipeline, app.cli"),
    ("a first compiled kernel from numba's cache",
     "from vo_core.direct.pyramid import _half; _half(numpy.zeros((4, 4), numpy.float32))"),
    ("rerun (and pyarrow), as fdmo run loads them",
     "app.cli.prepare_recording_process(); import rerun"),
    ("a recording: save + a first entity",
     "r = rerun.RecordingStream('memory'); r.save(TMP); r.log('p', rerun.Points3D(numpy.zeros((4, 3)))); r.flush()"),
)

FLOOR_SCRIPT = """
import sys
def status():
    fields = dict(line.split(':', 1) for line in open('/proc/self/status'))
    return [int(fields[k].split()[0]) * 1024 for k in ('VmRSS', 'RssAnon', 'RssFile')]
TMP = sys.argv[1]
for stage in sys.argv[2:]:
    exec(stage)
    print(*status(), flush=True)
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--no-rrd", action="store_true", help="the run without the Rerun recording")
    args = parser.parse_args()
    print(floor_table())
    print()
    print(run_table(args.folder, args.no_rrd))
    return 0


def floor_table() -> str:
    with tempfile.TemporaryDirectory() as tmp:
        output = subprocess.run(
            [sys.executable, "-c", FLOOR_SCRIPT, str(Path(tmp) / "floor.rrd"), *(code for _, code in FLOOR_STAGES)],
            capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[1],
        ).stdout.split("\n")
    rows, previous = [], 0
    for (name, _), line in zip(FLOOR_STAGES, output):
        rss, anon, files = (int(value) for value in line.split())
        rows.append((name, f"{rss / MB:.0f}", f"+{(rss - previous) / MB:.0f}", f"{anon / MB:.0f}", f"{files / MB:.0f}"))
        previous = rss
    return markdown_table(rows, ("after", "RSS MiB", "step", "anonymous", "files"))


def run_table(folder: Path, no_rrd: bool) -> str:
    with tempfile.TemporaryDirectory() as out:
        command = [sys.executable, "-m", "app", "run", str(folder), "--quiet", "--out", out]
        process = subprocess.Popen(command + (["--no-rrd"] if no_rrd else []), stdout=subprocess.DEVNULL,
                                   cwd=Path(__file__).resolve().parents[1])
        peak_sample: collections.Counter = collections.Counter()
        while True:
            pid, status, usage = os.wait4(process.pid, os.WNOHANG)
            if pid:
                process.returncode = os.waitstatus_to_exitcode(status)
                break
            sample = smaps_by_group(process.pid)
            if sum(sample.values()) > sum(peak_sample.values()):
                peak_sample = sample
            time.sleep(SAMPLE_PERIOD_S)
    if process.returncode:
        raise SystemExit(f"fdmo run failed on {folder} (exit status {process.returncode})")
    total = sum(peak_sample.values())
    rows = [(group, f"{size / MB:.1f}") for group, size in peak_sample.most_common(TOP_GROUPS)]
    rows.append(("the rest", f"{(total - sum(size for _, size in peak_sample.most_common(TOP_GROUPS))) / MB:.1f}"))
    rows.append(("**sampled peak**", f"**{total / MB:.1f}**"))
    rows.append(("peak RSS (os.wait4)", f"{usage.ru_maxrss / 1024:.1f}"))
    return markdown_table(rows, ("mapping", "RSS MiB"))


def smaps_by_group(pid: int) -> collections.Counter:
    """Resident bytes of a process per mapping group (the heap, anonymous memory, each library); empty once the
    process is gone."""
    groups: collections.Counter = collections.Counter()
    group = "[anon]"
    try:
        with open(f"/proc/{pid}/smaps") as smaps:
            for line in smaps:
                if re.match(r"^[0-9a-f]+-[0-9a-f]+ ", line):
                    fields = line.split(maxsplit=5)
                    group = mapping_group(fields[5].strip() if len(fields) > 5 else "")
                elif line.startswith("Rss:"):
                    groups[group] += int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError):
        return collections.Counter()
    return groups


def mapping_group(path: str) -> str:
    """A mapping's group: [heap], [anon] (also the stacks), or the Python package / library the file belongs to."""
    if not path or path.startswith("[") and path != "[heap]":
        return "[anon]"
    if path == "[heap]":
        return path
    package = re.search(r"site-packages/([^/]+)", path)
    if package:
        return re.sub(r"\.libs$", "", package.group(1))  # numpy.libs (its OpenBLAS) counts with numpy
    return os.path.basename(path)


if __name__ == "__main__":
    raise SystemExit(main())
