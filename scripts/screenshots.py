"""The README's screenshots of the viser page and of the Rerun web viewer, from one real run.

    python3 scripts/screenshots.py [SEQUENCE] [--method fdmo] [--out docs/images] [--run-options "--jump 60:20"]

Runs ``fdmo run SEQUENCE --viser`` into a temporary folder and opens the page, which starts the playback (at the
sequence's frame rate); once the page says the sequence finished (the page stays up), screenshots it. Then ends
the run (the recording is finished on the way out), serves its recording.rrd with ``rerun --serve-web --bind
127.0.0.1`` and screenshots the web viewer. The default run options make a backward jump that the bundled
sequence's feature map recovers from, so both screenshots show a divergence and a recovery. Needs Chromium
(``apt-get install chromium``) and playwright-core for Node (``npm install --prefix /tmp/pw playwright-core``;
set NODE_PATH=/tmp/pw/node_modules).
"""

from __future__ import annotations

import argparse
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "scripts" / "screenshot.cjs"
RUN_TIMEOUT_S = 600  # for the run to play the whole sequence, once the page has started it
VIEWER_WAIT_S = 240  # for the Rerun web viewer (software WebGL, slow on a busy machine) to load the recording
FINISHED = "sequence finished"  # what the viser page's status says at the end
DEFAULT_RUN_OPTIONS = "--jump 60:20"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", nargs="?", help="dataset folder (default: the bundled sequence)")
    parser.add_argument("--method", default="fdmo")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    parser.add_argument("--viser-port", type=int, default=8091)
    parser.add_argument("--rerun-ports", type=int, nargs=2, default=(9091, 9877), metavar=("WEB", "GRPC"))
    parser.add_argument("--size", default="1600x1000")
    parser.add_argument("--run-options", default=DEFAULT_RUN_OPTIONS,
                        help="more options for fdmo run, in one string (default: %(default)s)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as results:
        run_dir = Path(results) / "run"
        command = [sys.executable, "-m", "app", "run", *([args.sequence] if args.sequence else []),
                   "--method", args.method, "--viser", "--port", str(args.viser_port), "--out", str(run_dir),
                   "--quiet", *shlex.split(args.run_options)]
        with running(command, cwd=REPO, log=Path(results) / "run.log") as run:
            wait_for_page(run, args.viser_port)
            screenshot(f"http://127.0.0.1:{args.viser_port}", args.out / "viser.png", RUN_TIMEOUT_S, args.size,
                       until=FINISHED)
        web_port, grpc_port = args.rerun_ports
        viewer = ["rerun", "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web_port),
                  "--port", str(grpc_port), str(run_dir / "recording.rrd")]
        with running(viewer, cwd=REPO, log=Path(results) / "rerun.log"):
            time.sleep(3.0)
            source = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
            screenshot(f"http://127.0.0.1:{web_port}?url={source}", args.out / "rerun.png", VIEWER_WAIT_S, args.size)
    print(f"screenshots in {args.out}")
    return 0


class running:
    """A background process for the duration of a with-block, ended (by its own id) afterwards."""

    def __init__(self, command: list[str], cwd: Path, log: Path):
        self.command, self.cwd, self.log = command, cwd, log

    def __enter__(self) -> subprocess.Popen:
        self.output = open(self.log, "w")
        # A session of its own: the `rerun` command is a wrapper that starts the viewer as its child, and the
        # whole group must end with the block.
        self.process = subprocess.Popen(self.command, cwd=self.cwd, stdout=self.output, stderr=subprocess.STDOUT,
                                        start_new_session=True)
        self.process.log = self.log
        return self.process

    def __exit__(self, *exc) -> None:
        os.killpg(self.process.pid, signal.SIGTERM)
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
        self.output.close()


def wait_for_page(run: subprocess.Popen, port: int) -> None:
    """The page is served once the run has opened the sequence and built the odometry."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while time.monotonic() < deadline:
        if run.poll() is not None:
            raise RuntimeError(f"fdmo run exited ({run.returncode}):\n{run.log.read_text()[-2000:]}")
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=2).close()
            return
        except OSError:
            time.sleep(1.0)
    raise TimeoutError(f"the page was not served within {RUN_TIMEOUT_S} s")


def screenshot(url: str, path: Path, wait_s: float, size: str, until: str | None = None) -> None:
    environment = {**os.environ, "NODE_PATH": os.environ.get("NODE_PATH", "/tmp/pw/node_modules")}
    subprocess.run(["node", str(SCREENSHOT), url, str(path), str(wait_s), size, *([until] if until else [])],
                   check=True, env=environment, timeout=wait_s + 120)
    print(f"{path} <- {url}")


if __name__ == "__main__":
    sys.exit(main())
