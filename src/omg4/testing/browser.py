"""Headless Chromium for the browser tests: started with software WebGL2 (SwiftShader) and driven over the DevTools
protocol (navigate, evaluate, screenshot), a static file server (:func:`served`) and the web player's page
(:func:`open_player`). ``CHROMIUM`` is None where Debian's ``chromium`` is missing."""

from __future__ import annotations

import base64
import functools
import http.server
import io
import json
import shutil
import socket
import subprocess
import threading
import time
import urllib.request
from contextlib import contextmanager

from PIL import Image

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
TIMEOUT_S = 60


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait(condition, what: str, timeout: float = TIMEOUT_S) -> None:
    end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.1)


class Browser:
    """Headless Chromium driven over the DevTools protocol (navigate, evaluate, screenshot)."""

    def __init__(self, profile):
        from websockets.sync.client import connect

        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", "--no-first-run", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--disable-quic", f"--user-data-dir={profile}",
             "--remote-debugging-port=0", "--window-size=960,540", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = profile / "DevToolsActivePort"
        # Chromium creates the file before it writes the port into it: wait for the port itself
        wait(lambda: active.exists() and active.read_text().split(), "Chromium's DevTools port")
        port = int(active.read_text().split()[0])
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        self.ws = connect(next(p for p in pages if p["type"] == "page")["webSocketDebuggerUrl"], max_size=None)
        self.calls = 0

    def call(self, method: str, wait_s: float = TIMEOUT_S, **params) -> dict:
        self.calls += 1
        self.ws.send(json.dumps({"id": self.calls, "method": method, "params": params}))
        while True:
            message = json.loads(self.ws.recv(timeout=wait_s))
            if message.get("id") == self.calls:
                return message["result"]

    def screenshot(self) -> Image.Image:
        return Image.open(io.BytesIO(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])))

    def close(self) -> None:
        self.ws.close()
        self.proc.terminate()
        self.proc.wait(timeout=10)

    def evaluate(self, expression: str, timeout: float = TIMEOUT_S):
        """The value of a JavaScript expression in the page (a promise is awaited); a thrown error fails."""
        result = self.call("Runtime.evaluate", timeout + 5, expression=expression, awaitPromise=True,
                           returnByValue=True, timeout=int(1000 * timeout))
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise AssertionError(f"page error: {details.get('exception', {}).get('description') or details.get('text')}")
        return result["result"].get("value")


class _Quiet(http.server.SimpleHTTPRequestHandler):
    requests: list | None = None

    def log_message(self, *args):
        pass

    def log_request(self, code="-", size="-"):
        if self.requests is not None:
            self.requests.append((self.path, int(code)))


@contextmanager
def served(folder, requests: list | None = None):
    """A static file server of ``folder`` on a free local port; yields its base URL. With ``requests``, each request's
    ``(path, status)`` is appended to it."""
    handler = type("_Recording", (_Quiet,), {"requests": requests})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=str(folder)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


def open_player(browser: Browser, url: str, timeout: float = 120) -> dict:
    """Navigate to the player at ``url`` and wait until its first frame or its error: ``{"ready": …}`` or
    ``{"error": name, "message": text}``."""
    browser.call("Page.navigate", url=url)
    end = time.monotonic() + 30
    ready = f"location.href === {json.dumps(url)} && typeof window.omg4Ready === 'object'"
    while browser.evaluate(ready) is not True:
        if time.monotonic() > end:
            raise AssertionError(f"the player at {url} did not start")
        time.sleep(0.05)
    return browser.evaluate("window.omg4Ready.then(ready => ({ready}), err => ({error: err.name, message: "
                            "document.getElementById('message').textContent}))", timeout=timeout)
