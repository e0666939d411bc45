"""``kamino.viz.html`` in a real browser, network off: the page draws the bodies, and its time slider moves them.

A headless Chromium (Debian's ``chromium-headless-shell`` or ``chromium``, or the executable that
``KAMINO_TEST_CHROMIUM`` names) opens a written page from disk. WebGL runs on SwiftShader, Chromium's CPU renderer,
so no GPU or display is needed. The test drives the browser through the DevTools protocol over a pipe (Chromium's
``--remote-debugging-pipe``: JSON messages separated by NUL bytes on file descriptors 3 and 4), which needs only the
standard library. The network is off three ways: every host name resolves to nothing, the page's target is
emulated offline, and every request the page makes is recorded and must be a ``file:``, ``blob:`` or ``data:`` URL.

Where no Chromium is installed (CI's machine), the test is skipped and says so.
"""

from __future__ import annotations

import base64
import io
import json
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import kamino
from kamino import viz

pytestmark = pytest.mark.slow

#: executables tried in this order when ``KAMINO_TEST_CHROMIUM`` is unset
CHROMIUM_NAMES = ("chromium-headless-shell", "chromium", "chromium-browser", "chrome-headless-shell",
                  "google-chrome")
#: the page's size in CSS pixels (one device pixel each): small, since SwiftShader renders on the CPU
WIDTH, HEIGHT = 480, 360
#: the page's background colour (``viewer.html``: the body's and the three.js scene's)
BACKGROUND = np.array([0xF4, 0xF5, 0xF7])
#: a pixel is drawn when a channel differs from another image by more than this (antialiased edges differ by less)
PIXEL_TOLERANCE = 8
#: the DevTools protocol's key for the attached page a message is to or from (flat mode)
PAGE_KEY = "sessionId"
#: seconds any one browser reply may take (the page parses 0.7 MB of JavaScript and renders on the CPU)
REPLY_TIMEOUT = 60.0


#: ``python -c`` source: move the descriptors ``argv[1]`` and ``argv[2]`` to 3 and 4 (through numbers above 9, so
#: that neither overwrites the other), then execute ``argv[3:]`` (a shell cannot: dash takes one-digit numbers only)
_MOVE_FDS = """import fcntl, os, sys
fds = [int(a) for a in sys.argv[1:3]]
high = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in fds]
for fd in fds:
    os.close(fd)
for fd, target in zip(high, (3, 4)):
    os.dup2(fd, target)
    os.close(fd)
os.execv(sys.argv[3], sys.argv[3:])
"""


def _chromium() -> str | None:
    """The Chromium executable to run, or ``None`` where none is installed."""
    named = os.environ.get("KAMINO_TEST_CHROMIUM")
    if named:
        return shutil.which(named)
    return next((path for path in map(shutil.which, CHROMIUM_NAMES) if path), None)


def _chromium_args(profile: Path) -> list[str]:
    """Chromium's options: headless, driven through the pipe, a fresh profile, no network, WebGL on the CPU."""
    return ["--headless", "--no-sandbox", "--remote-debugging-pipe", f"--user-data-dir={profile}",
            "--no-first-run", "--no-default-browser-check", "--disable-extensions", "--mute-audio",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            "--disable-dev-shm-usage",  # a container's small /dev/shm does not crash the renderer
            "--host-resolver-rules=MAP * ~NOTFOUND",  # no host name resolves
            "--use-angle=swiftshader", "--enable-unsafe-swiftshader",  # WebGL on SwiftShader
            f"--window-size={WIDTH},{HEIGHT}", "about:blank"]


class DevTools:
    """A headless Chromium driven through the DevTools protocol on a pipe.

    ``call`` sends one command and returns its result; the events that arrive meanwhile are kept in ``events``.
    """

    def __init__(self, executable: str, profile: Path) -> None:
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        self._log = open(profile / "chromium.log", "w+b")  # closed in close()
        # a small Python process (_MOVE_FDS) puts the pipe ends on the descriptors 3 and 4, then becomes Chromium
        command = [sys.executable, "-c", _MOVE_FDS, str(to_browser_r), str(from_browser_w), executable,
                   *_chromium_args(profile)]
        self._proc = subprocess.Popen(command, pass_fds=(to_browser_r, from_browser_w), stdin=subprocess.DEVNULL,
                                      stdout=self._log, stderr=self._log)
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict[str, Any]] = []

    def _message(self, deadline: float) -> dict[str, Any]:
        """The next message from the browser."""
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._from_browser], [], [], left)[0]:
                raise TimeoutError(f"Chromium did not answer in {REPLY_TIMEOUT} s; its log: {self.log()}")
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise RuntimeError(f"Chromium closed its DevTools pipe; its log: {self.log()}")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def call(self, method: str, page: str | None = None, **params: Any) -> dict[str, Any]:
        """Send a command (to the attached page ``page`` when given, else to the browser) and return its result."""
        self._next_id += 1
        command: dict[str, Any] = {"id": self._next_id, "method": method, "params": params}
        if page is not None:
            command[PAGE_KEY] = page
        os.write(self._to_browser, json.dumps(command).encode() + b"\0")
        deadline = time.monotonic() + REPLY_TIMEOUT
        while True:
            message = self._message(deadline)
            if message.get("id") != self._next_id:
                self.events.append(message)
            elif "error" in message:
                raise RuntimeError(f"{method}: {message['error']}")
            else:
                return message["result"]

    def wait_for(self, method: str, page: str, deadline: float) -> None:
        """Read until the attached page ``page`` has sent an event ``method``."""
        while not any(e.get("method") == method and e.get(PAGE_KEY) == page for e in self.events):
            self.events.append(self._message(deadline))

    def log(self) -> str:
        self._log.seek(0)
        return self._log.read()[-3000:].decode(errors="replace")

    def close(self) -> None:
        os.close(self._to_browser)  # Chromium exits when its pipe closes
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        os.close(self._from_browser)
        self._log.close()


class Page:
    """One page of the browser, attached in flat mode."""

    def __init__(self, browser: DevTools) -> None:
        self.browser = browser
        target = browser.call("Target.createTarget", url="about:blank")["targetId"]
        self.id = browser.call("Target.attachToTarget", targetId=target, flatten=True)[PAGE_KEY]
        for domain in ("Page", "Runtime", "Network"):
            self.call(f"{domain}.enable")
        self.call("Network.emulateNetworkConditions", offline=True, latency=0, downloadThroughput=-1,
                  uploadThroughput=-1)
        self.call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1,
                  mobile=False)

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        return self.browser.call(method, self.id, **params)

    def evaluate(self, expression: str) -> Any:
        """The value of a JavaScript expression in the page (a promise is awaited)."""
        reply = self.call("Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in reply:
            raise RuntimeError(f"{expression!r} threw: {reply['exceptionDetails']}")
        return reply["result"].get("value")

    def next_frames(self) -> None:
        """Wait until the page has drawn two more animation frames (the viewer renders in each)."""
        self.evaluate("new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")

    def screenshot(self, clip: dict[str, float]) -> np.ndarray:
        """The pixels of ``clip`` (CSS pixels), as an ``[h, w, 3]`` uint8 array."""
        from PIL import Image

        png = self.call("Page.captureScreenshot", format="png", clip={**clip, "scale": 1})["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(png))).convert("RGB"))

    def requested_urls(self) -> list[str]:
        return [e["params"]["request"]["url"] for e in self.browser.events
                if e.get("method") == "Network.requestWillBeSent" and e.get(PAGE_KEY) == self.id]

    def problems(self) -> list[str]:
        """The page's uncaught exceptions and console errors so far."""
        out = []
        for e in (e for e in self.browser.events if e.get(PAGE_KEY) == self.id):
            if e.get("method") == "Runtime.exceptionThrown":
                out.append(json.dumps(e["params"]["exceptionDetails"])[:500])
            elif e.get("method") == "Runtime.consoleAPICalled" and e["params"]["type"] == "error":
                out.append(json.dumps(e["params"]["args"])[:500])
        return out


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    executable = _chromium()
    if executable is None:
        named = os.environ.get("KAMINO_TEST_CHROMIUM")
        pytest.skip(f"no headless browser: KAMINO_TEST_CHROMIUM={named!r} is not an executable" if named else
                    f"no headless browser: none of {', '.join(CHROMIUM_NAMES)} is on PATH (Debian: apt-get install "
                    "chromium-headless-shell; or set KAMINO_TEST_CHROMIUM)")
    pytest.importorskip("PIL", reason="the screenshots are decoded with Pillow")
    devtools = DevTools(executable, tmp_path_factory.mktemp("chromium"))
    try:
        yield devtools
    finally:
        devtools.close()


def _moving_fourbar(num_frames: int) -> tuple[kamino.Model, kamino.State]:
    """A four-bar trajectory built by hand (no compilation): the mechanism at rest in the first frame, then
    carried along +x by 0.04 m per frame, without turning."""
    model = kamino.models.fourbar()
    state = kamino.init_state(model)
    traj = jax.tree.map(lambda x: jnp.stack([x] * num_frames), state)
    q = np.repeat(np.asarray(model.body_q0)[None], num_frames, axis=0)
    q[..., 0] += 0.04 * np.arange(num_frames)[:, None]
    time_ = (np.arange(num_frames) / 240.0)[:, None]
    return model, traj.replace(body_q=jnp.asarray(q), time=jnp.asarray(time_))


def _drawn(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Where ``image`` differs from ``reference`` (an image or a colour) by more than antialiasing does."""
    return np.any(np.abs(image.astype(int) - reference.astype(int)) > PIXEL_TOLERANCE, axis=-1)


def test_page_draws_offline_and_its_slider_moves_the_bodies(browser, tmp_path):
    model, traj = _moving_fourbar(num_frames=6)
    path = tmp_path / "fourbar.html"
    viz.html(model, traj, path, show_contacts=False)
    page = Page(browser)
    deadline = time.monotonic() + REPLY_TIMEOUT
    page.call("Page.navigate", url=path.as_uri())
    browser.wait_for("Page.loadEventFired", page.id, deadline)  # after the page's modules have loaded
    # nothing came from the network: the page, and the libraries it carries (blob: modules)
    urls = page.requested_urls()
    assert urls and all(url.split(":", 1)[0] in {"file", "blob", "data"} for url in urls), urls
    # the viewer is up when it has shown its first frame (the clock names it); a failed page says why in #info
    while not page.evaluate('document.getElementById("clock").textContent'):
        failed = page.evaluate('document.getElementById("info").textContent')
        assert not failed.startswith("The viewer failed"), f"{failed}; {page.problems()}"
        assert time.monotonic() < deadline, f"the viewer did not start: {failed}; {page.problems()}"
        time.sleep(0.05)
    assert page.problems() == []
    # the canvas alone, without the overlaid title text
    page.evaluate('document.getElementById("info").style.visibility = "hidden"')
    clip = page.evaluate('(({x, y, width, height}) => ({x, y, width, height}))('
                         'document.querySelector("#view canvas").getBoundingClientRect())')
    assert clip["width"] == WIDTH and clip["height"] > HEIGHT / 2, clip
    page.next_frames()
    first = page.screenshot(clip)

    # (a) not blank: the four bodies' spheres, frame axes, rods and joint markers cover 1.2 % of the canvas
    # (measured), a page that draws nothing 0 %
    drawn = _drawn(first, BACKGROUND).mean()
    assert drawn > 0.005, f"the canvas is blank: {drawn:.2%} of its pixels differ from the background"

    # (b) the slider, moved to the last frame as a user drags it, moves the bodies 0.2 m: the picture changes
    # (2.2 % of the pixels, measured: where the figure was and where it is)
    last = len(traj.time) - 1
    page.evaluate(f'(() => {{ const s = document.getElementById("slider"); s.value = {last};'
                  f' s.dispatchEvent(new Event("input")); }})()')
    page.next_frames()
    moved = page.screenshot(clip)
    assert page.evaluate('document.getElementById("clock").textContent').endswith(f"(step {last})")
    changed = _drawn(moved, first).mean()
    assert changed > 0.005, f"moving the slider changed {changed:.2%} of the canvas"
    assert _drawn(moved, BACKGROUND).mean() > 0.005  # the bodies are still in view
    # and back: the first frame's picture again, so the change came from the frame shown
    page.evaluate('(() => { const s = document.getElementById("slider"); s.value = 0;'
                  ' s.dispatchEvent(new Event("input")); })()')
    page.next_frames()
    assert _drawn(page.screenshot(clip), first).mean() < 1e-3
