"""Headless chromium driven over the DevTools protocol, for the tests that need a real browser.

`Browser` starts Debian's chromium headless, connects to its page target (a websocket, through the `websockets`
package Prefect already depends on), loads a page (a file or an http:// address) and reports every console message,
uncaught exception, browser log entry and network request; `chromium_or_fail` finds the executable or fails the test
(never skips) with the install command. Used by tests/test_dashboard.py (the HTML report) and tests/test_gltf.py
(three.js playing our GLB).
"""

import contextlib
import functools
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--no-first-run", "--no-default-browser-check", "--disable-dev-shm-usage", "--disable-extensions",
    "--disable-sync", "--mute-audio", "--hide-scrollbars", "--remote-debugging-port=0", "--window-size=1280,2000",
]


def chromium_or_fail() -> str:
    """The chromium executable; without one the test fails (a skip would let a missing browser pass unnoticed)."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        exe = shutil.which(name)
        if exe:
            return exe
    pytest.fail("chromium is not installed: run `sh scripts/system-deps.sh` as root "
                "(or `apt-get install -y chromium`); `make test` and .ci/run run it first")


class Browser:
    """Headless chromium and one page target, driven over the DevTools protocol."""

    def __init__(self, exe: str, profile: Path, timeout: float = 60.0):
        from websockets.sync.client import connect

        self.timeout = timeout
        self.log = profile.parent / f"{profile.name}.stderr"
        profile.mkdir(parents=True, exist_ok=True)
        with open(self.log, "wb") as err:
            self.proc = subprocess.Popen([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
                                         stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
        try:
            port_file = profile / "DevToolsActivePort"
            deadline = time.monotonic() + timeout
            while not (port_file.exists() and len(port_file.read_text().split()) >= 2):
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"chromium did not start: {self.log.read_text(errors='replace')[-2000:]}")
                time.sleep(0.05)
            port = port_file.read_text().split()[0]
            # The page target: the tab chromium opened on about:blank; its endpoint is /devtools/page/<id>.
            with connect(f"ws://127.0.0.1:{port}{port_file.read_text().split()[1]}", proxy=None) as browser:
                browser.send(json.dumps({"id": 1, "method": "Target.getTargets"}))
                while True:
                    reply = json.loads(browser.recv(timeout=timeout))
                    if reply.get("id") == 1:
                        break
            page = next(t for t in reply["result"]["targetInfos"] if t["type"] == "page")
            self.ws = connect(f"ws://127.0.0.1:{port}/devtools/page/{page['targetId']}", proxy=None, max_size=None)
        except BaseException:
            self.kill()
            raise
        self.next_id = 0
        self.events: list[dict] = []

    def send(self, method: str, params: dict | None = None) -> dict:
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params or {}}))
        deadline = time.monotonic() + self.timeout
        while True:
            message = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]
            if "method" in message:
                self.events.append(message)

    def wait_for(self, event: str) -> dict:
        deadline = time.monotonic() + self.timeout
        while True:
            for e in self.events:
                if e["method"] == event:
                    self.events.remove(e)
                    return e
            message = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
            if "method" in message:
                self.events.append(message)

    def load(self, page: Path | str) -> dict:
        """Open `page` (a file, or an address as a string); after its load event, the page's problems and the
        state of its images."""
        self.events.clear()
        for domain in ("Page", "Runtime", "Log", "Network"):
            self.send(f"{domain}.enable")
        self.send("Emulation.setDeviceMetricsOverride", {"width": 1280, "height": 2000, "deviceScaleFactor": 1,
                                                          "mobile": False})
        url = page.resolve().as_uri() if isinstance(page, Path) else page
        self.send("Page.navigate", {"url": url})
        self.wait_for("Page.loadEventFired")
        images = self.send("Runtime.evaluate", {"returnByValue": True, "awaitPromise": True, "expression": """
            Promise.all([...document.images].map(img => img.decode().then(() => true, () => false)))
              .then(() => [...document.images].map(img => ({id: img.id, alt: img.alt, complete: img.complete,
                                                             width: img.naturalWidth, height: img.naturalHeight})))
        """})["result"]["value"]
        self.send("Runtime.evaluate", {"expression": "0"})   # flush: events queued before this reply are in
        errors = []
        for e in self.events:
            p = e["params"]
            if e["method"] == "Runtime.consoleAPICalled" and p["type"] in ("error", "assert", "warning"):
                errors.append(f"console.{p['type']}: " + " ".join(str(a.get("value", a.get("description")))
                                                                  for a in p["args"]))
            elif e["method"] == "Runtime.exceptionThrown":
                errors.append(f"exception: {p['exceptionDetails'].get('text')}")
            elif e["method"] == "Log.entryAdded" and p["entry"]["level"] in ("error", "warning"):
                errors.append(f"log {p['entry']['source']}: {p['entry']['text']}")
            elif e["method"] == "Network.loadingFailed":
                errors.append(f"load failed: {p.get('blockedReason') or p.get('errorText')}")
        requests = [e["params"]["request"]["url"] for e in self.events if e["method"] == "Network.requestWillBeSent"]
        return {"errors": errors, "requests": requests, "images": images}

    def screenshot(self, path: Path) -> Path:
        import base64

        path.write_bytes(base64.b64decode(self.send("Page.captureScreenshot", {"format": "png"})["data"]))
        return path

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGKILL)   # chromium and the renderer processes it started
            except ProcessLookupError:
                pass
        self.proc.wait(timeout=30)

    def close(self) -> None:
        from websockets.exceptions import WebSocketException

        with contextlib.suppress(RuntimeError, OSError, TimeoutError, WebSocketException):
            self.send("Browser.close")
        with contextlib.suppress(OSError, WebSocketException, subprocess.TimeoutExpired):
            self.ws.close()
            self.proc.wait(timeout=10)
        self.kill()


class _QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, format, *args):  # noqa: A002 (the base class's name)
        pass


@contextlib.contextmanager
def serve_folder(root: Path, page: str, node_modules: Path):
    """Serve `root` on 127.0.0.1 with `page` as its index.html and `node_modules` linked in; yields the base address."""
    (root / "index.html").write_text(page, encoding="utf-8")
    (root / "node_modules").symlink_to(node_modules, target_is_directory=True)
    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(_QuietHandler, directory=str(root)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)
