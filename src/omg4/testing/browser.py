"""Headless Chromium for the browser tests: started with software WebGL2 (SwiftShader) and driven over the DevTools
protocol (navigate, evaluate, screenshot), a static file server (:func:`served`), the web player's page
(:func:`open_player`), a canvas's picture (:func:`data_url_image`), and the decoded arrays' digests on both sides
(:data:`DIGESTS`, :func:`python_digests`). ``CHROMIUM`` is None where Debian's ``chromium`` is missing."""

from __future__ import annotations

import base64
import functools
import hashlib
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

import numpy as np
from PIL import Image

from omg4.codec.container import read_container
from omg4.codec.payload import decode_payload
from omg4.codec.sequence import SegmentDecoder, read_index, read_segment

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


# the page's decoder (the export's decoder/payload.js on model.omg4), every decoded array as the SHA-256 of its bytes
# (fp16 bit patterns, int32 indices)
DIGESTS = """import('./decoder/payload.js').then(async ({ decodePayload }) => {
  const bytes = new Uint8Array(await (await fetch('model.omg4', { cache: 'no-store' })).arrayBuffer());
  const p = await decodePayload(bytes);
  DIGEST_BODY
})"""
# the same of segment K of an exported sequence, decoded by the player's chain (sequence.js SegmentPayloads)
SEGMENT_DIGESTS = """import('./sequence.js').then(async ({ SegmentPayloads }) => {
  const listing = await (await fetch('sequence.json', { cache: 'no-store' })).json();
  const segments = listing.segments.map((s) => ({ url: s.file, reference: s.reference }));
  const fetchBytes = async (url) => new Uint8Array(await (await fetch(url, { cache: 'no-store' })).arrayBuffer());
  const p = await new SegmentPayloads(segments, fetchBytes).payload(SEGMENT);
  DIGEST_BODY
})"""
DIGEST_BODY = """const hex = async (a) => Array.from(new Uint8Array(await crypto.subtle.digest('SHA-256', a))).map(
    (b) => b.toString(16).padStart(2, '0')).join('');
  const out = { xyz: await hex(p.xyz), t: await hex(p.t) };
  for (const [k, a] of Object.entries(p.attributes)) {
    for (const [j, c] of a.codebooks.entries()) out[`${k}.codebook${j}`] = await hex(c.values);
    for (const [j, c] of a.indices.entries()) out[`${k}.index${j}`] = await hex(c);
  }
  for (const [k, q] of Object.entries(p.quaternions)) out[`quat.${k}`] = await hex(q);
  for (const [k, m] of Object.entries(p.mlp)) out[`mlp.${k}`] = await hex(m.values);
  return out;"""
DIGESTS, SEGMENT_DIGESTS = (page.replace("DIGEST_BODY", DIGEST_BODY) for page in (DIGESTS, SEGMENT_DIGESTS))


def data_url_image(data_url: str) -> np.ndarray:
    """The RGB picture [H, W, 3] (float64, 0–255) of a canvas's ``toDataURL('image/png')``."""
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data_url.split(",", 1)[1]))).convert("RGB"), np.float64)


def python_digests(path, segment: int | None = None) -> dict[str, str]:
    """The same digests of the Python decoder's arrays (of one segment of a sequence file, decoded after its chain)."""
    if segment is None:
        header, _ = read_container(path)
        payload = decode_payload(path)
    else:
        header, _ = read_container(read_segment(path, read_index(path).segments[segment]))
        payload = SegmentDecoder(path).payload(segment)
    digest = lambda a: hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()  # noqa: E731
    fp16 = lambda a: digest(np.asarray(a, np.float16).view(np.uint16))  # noqa: E731
    out = {"xyz": fp16(payload.xyz), "t": fp16(payload.t)}
    for name, qa in payload.attributes.items():
        if name in header.get("quaternions", []):
            out[f"quat.{name}"] = fp16(qa.codebooks[0])
            continue
        for j, (cb, ix) in enumerate(zip(qa.codebooks, qa.indices)):
            out[f"{name}.codebook{j}"], out[f"{name}.index{j}"] = fp16(cb), digest(np.asarray(ix, np.int32))
    out.update({f"mlp.{name}": fp16(w) for name, w in payload.mlp.items()})
    return out


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
