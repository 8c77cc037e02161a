"""The README's screenshots of the viser page and of the Rerun web viewer, from one real run.

    python3 scripts/screenshots.py [SEQUENCE] [--method direct] [--out docs/images] [--run-options "--drop 40:5"]

Runs ``fdmo run SEQUENCE --viser`` into a temporary folder, waits for the sequence to finish (the page stays
up), screenshots the page; then serves the run's recording.rrd with ``rerun --serve-web --bind 127.0.0.1`` and
screenshots the web viewer. Needs Chromium (``apt-get install chromium``) and playwright-core for Node
(``npm install --prefix /tmp/pw playwright-core``; set NODE_PATH=/tmp/pw/node_modules).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
import time
import urllib.parse
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "scripts" / "screenshot.cjs"
RUN_TIMEOUT_S = 600
PAGE_WAIT_S = 10  # for the viser client to connect and draw
VIEWER_WAIT_S = 45  # for the Rerun web viewer (software WebGL) to load the recording and draw its last frame


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", nargs="?", help="dataset folder (default: the bundled sequence)")
    parser.add_argument("--method", default="direct")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "images")
    parser.add_argument("--viser-port", type=int, default=8091)
    parser.add_argument("--rerun-ports", type=int, nargs=2, default=(9091, 9877), metavar=("WEB", "GRPC"))
    parser.add_argument("--size", default="1600x1000")
    parser.add_argument("--run-options", default="", help="more options for fdmo run, in one string")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as results:
        run_dir = Path(results) / "run"
        command = [sys.executable, "-m", "app", "run", *([args.sequence] if args.sequence else []),
                   "--method", args.method, "--viser", "--port", str(args.viser_port), "--out", str(run_dir),
                   "--quiet", *shlex.split(args.run_options)]
        with running(command, cwd=REPO, log=Path(results) / "run.log") as run:
            wait_for_completion(run, run_dir / "metrics.json")
            screenshot(f"http://127.0.0.1:{args.viser_port}", args.out / "viser.png", PAGE_WAIT_S, args.size)
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


def wait_for_completion(run: subprocess.Popen, metrics_file: Path) -> None:
    """metrics.json is written when a pass ends; wait for a completed one."""
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while time.monotonic() < deadline:
        if run.poll() is not None:
            raise RuntimeError(f"fdmo run exited ({run.returncode}):\n{run.log.read_text()[-2000:]}")
        if metrics_file.is_file() and json.loads(metrics_file.read_text()).get("status") == "completed":
            time.sleep(2.0)  # the page's next refresh
            return
        time.sleep(1.0)
    raise TimeoutError(f"the run did not complete within {RUN_TIMEOUT_S} s")


def screenshot(url: str, path: Path, wait_s: float, size: str) -> None:
    environment = {**os.environ, "NODE_PATH": os.environ.get("NODE_PATH", "/tmp/pw/node_modules")}
    subprocess.run(["node", str(SCREENSHOT), url, str(path), str(wait_s), size], check=True, env=environment,
                   timeout=wait_s + 120)
    print(f"{path} <- {url}")


if __name__ == "__main__":
    sys.exit(main())
