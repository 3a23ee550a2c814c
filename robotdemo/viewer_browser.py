"""Headless Chromium driven over the DevTools protocol: inspect a Meshcat page's three.js scene, screenshot it.

Used by the viewer's browser tests and to make the README's screenshot::

    from robotdemo.viewer_browser import screenshot
    screenshot("http://127.0.0.1:7000/static/", "docs/meshcat_scene.png")

Needs a Chromium binary (Debian: ``apt-get install chromium``); the websocket client is tornado's, which
meshcat already depends on, so nothing else is installed. Chromium runs with its own throw-away profile,
no network services, and software WebGL (SwiftShader), so it works on machines without a GPU.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")

MESH_PATHS_JS = """(() => {
  const out = [];
  viewer.scene.traverse((o) => {
    if (!o.isMesh) return;
    const names = [];
    for (let n = o; n && n !== viewer.scene; n = n.parent) names.unshift(n.name);
    out.push("/" + names.join("/"));
  });
  return out;
})()"""
"""JavaScript: the path (``/meshcat/robot/link1/visual0/<object>``) of every mesh in the page's three.js scene."""

NEXT_FRAME_JS = """new Promise((resolve) => { viewer.set_dirty();
  requestAnimationFrame(() => requestAnimationFrame(() => resolve(true))); })"""
"""JavaScript: resolves once the viewer has rendered two more frames."""


class BrowserError(RuntimeError):
    """Chromium could not be started or driven."""


def find_chromium() -> str | None:
    """Path of a Chromium/Chrome binary on PATH (``$CHROMIUM`` wins), or ``None``."""
    explicit = os.environ.get("CHROMIUM")
    if explicit:
        return shutil.which(explicit) or (explicit if Path(explicit).is_file() else None)
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


def _no_proxy_opener() -> urllib.request.OpenerDirector:
    return urllib.request.build_opener(urllib.request.ProxyHandler({}))


class HeadlessChromium:
    """One headless Chromium with one page, driven over the DevTools protocol. Use as a context manager."""

    def __init__(self, executable: str | None = None, width: int = 1280, height: int = 800,
                 timeout_s: float = 30.0) -> None:
        executable = executable or find_chromium()
        if executable is None:
            raise BrowserError("no Chromium found (install Debian's 'chromium' package or set $CHROMIUM)")
        self.timeout_s = timeout_s
        self.profile = tempfile.mkdtemp(prefix="robotdemo-chromium-")
        args = [executable, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--no-proxy-server", "--mute-audio", "--hide-scrollbars",
                "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
                f"--window-size={width},{height}", f"--user-data-dir={self.profile}",
                "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0", "about:blank"]
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, start_new_session=True)
        self._loop = asyncio.new_event_loop()
        self._ws = None
        self._next_id = 0
        try:
            port = self._devtools_port()
            self._ws = self._run(self._connect(port))
            self.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                      mobile=False)
        except BaseException:
            self.close()
            raise

    # -- set-up ---------------------------------------------------------------------------------------------
    def _devtools_port(self) -> int:
        marker = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise BrowserError(f"Chromium exited with status {self.proc.returncode} at start-up")
            if marker.is_file():
                lines = marker.read_text().split()
                if lines:
                    return int(lines[0])
            time.sleep(0.05)
        raise BrowserError(f"Chromium opened no DevTools port within {self.timeout_s:.0f} s")

    async def _connect(self, port: int):
        from tornado.websocket import websocket_connect

        deadline = time.monotonic() + self.timeout_s
        while True:
            with _no_proxy_opener().open(f"http://127.0.0.1:{port}/json/list", timeout=5) as response:
                pages = [t for t in json.load(response) if t.get("type") == "page"]
            if pages:
                break
            if time.monotonic() > deadline:
                raise BrowserError("Chromium shows no page to drive")
            await asyncio.sleep(0.05)
        return await websocket_connect(pages[0]["webSocketDebuggerUrl"], max_message_size=256 * 1024 * 1024)

    def _run(self, coroutine: Any) -> Any:
        return self._loop.run_until_complete(asyncio.wait_for(coroutine, self.timeout_s))

    async def _call(self, method: str, **params: Any) -> dict:
        self._next_id += 1
        request_id = self._next_id
        await self._ws.write_message(json.dumps({"id": request_id, "method": method, "params": params}))
        while True:
            message = await self._ws.read_message()
            if message is None:
                raise BrowserError("the DevTools connection closed")
            reply = json.loads(message)
            if reply.get("id") == request_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error'].get('message')}")
                return reply.get("result", {})

    # -- driving ----------------------------------------------------------------------------------------------
    def call(self, method: str, **params: Any) -> dict:
        """One DevTools command, e.g. ``call("Page.navigate", url=...)``; returns its result."""
        return self._run(self._call(method, **params))

    def open(self, url: str) -> None:
        """Load ``url`` and wait for the document to finish loading."""
        self.call("Page.navigate", url=url)
        self.wait_for("document.readyState === 'complete' && document.URL !== 'about:blank'")

    def evaluate(self, expression: str) -> Any:
        """Evaluate JavaScript in the page (promises awaited); returns the value, or raises on an exception."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text")
            raise BrowserError(f"JavaScript error: {text}")
        return result.get("result", {}).get("value")

    def wait_for(self, expression: str, timeout_s: float | None = None, poll_s: float = 0.1) -> Any:
        """Evaluate ``expression`` until it is truthy (errors count as not yet); returns its value."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        last_error = None
        while True:
            try:
                value = self.evaluate(expression)
                if value:
                    return value
            except BrowserError as exc:
                last_error = exc
            if time.monotonic() > deadline:
                raise BrowserError(f"timed out waiting for {expression!r}" + (f" ({last_error})" if last_error else ""))
            time.sleep(poll_s)

    def mesh_paths(self) -> list[str]:
        """Paths of every mesh in the page's three.js scene (Meshcat pages only)."""
        return self.evaluate(MESH_PATHS_JS) or []

    def next_frame(self) -> None:
        self.evaluate(NEXT_FRAME_JS)

    def screenshot_png(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    # -- tear-down ------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop Chromium (its whole process group, which it was started in) and delete its profile."""
        if self._ws is not None:
            self._ws.close()
            self._ws = None
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        if not self._loop.is_closed():
            self._loop.close()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> "HeadlessChromium":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_for_meshcat_scene(browser: HeadlessChromium, expected_paths: list[str], timeout_s: float = 30.0) -> list[str]:
    """Wait until every expected path prefix has a mesh in the page's scene; returns all mesh paths."""
    needles = json.dumps(list(expected_paths))
    browser.wait_for(f"(() => {{ const paths = {MESH_PATHS_JS}; const needles = {needles};"
                     f" return needles.every((n) => paths.some((p) => p.startsWith(n))); }})()", timeout_s)
    return browser.mesh_paths()


def screenshot(url: str, path: str | Path, width: int = 1280, height: int = 800,
               expected_paths: list[str] | None = None, settle_s: float = 0.5) -> Path:
    """Open a Meshcat page in headless Chromium and save a PNG of it.

    Args:
        url: the live viewer's address or a recorded HTML file (``file:///...``).
        path: where to write the PNG (folders are created).
        expected_paths: mesh path prefixes to wait for before shooting (default: ``/meshcat/robot``).
        settle_s: extra time for textures and the first animation frames.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with HeadlessChromium(width=width, height=height) as browser:
        browser.open(url)
        wait_for_meshcat_scene(browser, expected_paths or ["/meshcat/robot"])
        time.sleep(settle_s)
        browser.next_frame()
        path.write_bytes(browser.screenshot_png())
    return path
