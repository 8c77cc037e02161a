"""A page in headless Chromium, driven over the DevTools protocol with the websockets client that viser already
depends on (no Node, no playwright): navigate, evaluate JavaScript, wait for a condition, click a button."""

from __future__ import annotations

import itertools
import json
import re
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

from websockets.sync.client import connect

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
START_TIMEOUT_S = 60.0


class ChromiumPage:
    """One tab of a headless Chromium started for it; ``close()`` ends that Chromium (by its process id)."""

    def __init__(self, url: str):
        # Chromium's helper processes can still write into the profile as the main one exits (CI saw rmtree fail
        # on a directory not empty): what is left of a scratch profile must not fail a test.
        self._profile = tempfile.TemporaryDirectory(ignore_cleanup_errors=True)
        log = Path(self._profile.name) / "chromium.log"
        self._log = open(log, "w")
        self.process = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
             "--disable-background-networking", "--disable-component-update", "--no-first-run",
             "--remote-debugging-port=0", f"--user-data-dir={self._profile.name}", "about:blank"],
            stdout=self._log, stderr=self._log,
        )
        self._ids = itertools.count(1)
        self._socket = connect(self._page_socket(log), max_size=None, open_timeout=START_TIMEOUT_S)
        self.call("Page.navigate", url=url)

    def _page_socket(self, log: Path) -> str:
        """The DevTools address of the blank tab, read from the port Chromium announces in its log."""
        deadline = time.monotonic() + START_TIMEOUT_S
        while time.monotonic() < deadline:
            found = re.search(r"DevTools listening on ws://[^:/]+:(\d+)/", log.read_text())
            if found:
                with urllib.request.urlopen(f"http://127.0.0.1:{found.group(1)}/json/list", timeout=10) as response:
                    targets = json.loads(response.read())
                return next(target["webSocketDebuggerUrl"] for target in targets if target["type"] == "page")
            if self.process.poll() is not None:
                break
            time.sleep(0.1)
        raise RuntimeError(f"chromium did not start:\n{log.read_text()[-2000:]}")

    def call(self, method: str, **params) -> dict:
        """One DevTools command; its result (the events that come in meanwhile are skipped)."""
        message_id = next(self._ids)
        self._socket.send(json.dumps({"id": message_id, "method": method, "params": params}))
        while True:
            message = json.loads(self._socket.recv(timeout=START_TIMEOUT_S))
            if message.get("id") == message_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (None while it throws: the page may still be loading)."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        return None if "exceptionDetails" in result else result["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 60.0):
        """Poll ``expression`` until it is truthy; its value."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(0.1)
        raise TimeoutError(f"the page never satisfied: {expression}")

    def click(self, text: str) -> None:
        """Click the button whose label is ``text`` (as a person would: a real mouse event on the button)."""
        self.wait_for(f"[...document.querySelectorAll('button')].some(b => b.textContent.trim() === {json.dumps(text)})")
        self.evaluate(f"[...document.querySelectorAll('button')].find(b => b.textContent.trim() === {json.dumps(text)})"
                      ".click()")

    def close(self) -> None:
        self._socket.close()
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self._log.close()
        self._profile.cleanup()
