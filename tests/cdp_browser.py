"""Headless Chromium driven over the Chrome DevTools Protocol (the `websockets` client), for the live-page tests.

    with Browser.launch(download_dir) as b:
        tab = b.open("http://127.0.0.1:8080/")
        tab.wait_for("window.livePage && window.livePage.stateMessages > 0")
        tab.click("#rec")
        tab.screenshot("page.png")
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from websockets.sync.client import connect

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


class CdpError(RuntimeError):
    pass


class _Session:
    """One DevTools WebSocket (the browser's or a tab's)."""

    def __init__(self, url: str):
        self.ws = connect(url, max_size=64 * 1024 * 1024, open_timeout=20)
        self._ids = itertools.count(1)
        self.events: list[dict] = []

    def call(self, method: str, timeout_s: float = 30.0, **params: Any) -> dict:
        i = next(self._ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        end = time.monotonic() + timeout_s
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise CdpError(f"{method}: no answer within {timeout_s} s")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == i:
                if "error" in msg:
                    raise CdpError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self.events.append(msg)

    def close(self) -> None:
        self.ws.close()


class Tab(_Session):
    def evaluate(self, expression: str, timeout_s: float = 30.0) -> Any:
        r = self.call("Runtime.evaluate", timeout_s, expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise CdpError(f"{expression[:80]}: {r['exceptionDetails'].get('exception', {}).get('description')}")
        return r["result"].get("value")

    def wait_for(self, expression: str, timeout_s: float = 20.0, poll_s: float = 0.05) -> Any:
        end = time.monotonic() + timeout_s
        value = None
        while time.monotonic() < end:
            value = self.evaluate(expression)
            if value:
                return value
            time.sleep(poll_s)
        raise CdpError(f"not true within {timeout_s} s: {expression} (last {value!r})")

    def click(self, selector: str) -> None:
        self.evaluate(f"document.querySelector({json.dumps(selector)}).click()")

    def text(self, selector: str) -> str:
        return self.evaluate(f"document.querySelector({json.dumps(selector)}).textContent")

    def mouse(self, kind: str, x: float, y: float, *, pressed: bool = False, clicks: int = 0) -> None:
        """One mouse event at viewport position (x, y) [CSS px]: ``kind`` mouseMoved / mousePressed /
        mouseReleased (left button)."""
        self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left" if pressed or clicks else "none",
                  buttons=1 if pressed else 0, clickCount=clicks)

    def click_at(self, x: float, y: float, clicks: int = 1) -> None:
        """A left click (``clicks=2``: a double click) at viewport position (x, y), as a user's mouse makes it."""
        self.mouse("mouseMoved", x, y)
        for n in range(1, clicks + 1):
            self.mouse("mousePressed", x, y, pressed=True, clicks=n)
            self.mouse("mouseReleased", x, y, clicks=n)

    def drag(self, x0: float, y0: float, x1: float, y1: float, steps: int = 8) -> None:
        """Press the left button at (x0, y0), move to (x1, y1) in ``steps``, release."""
        self.mouse("mouseMoved", x0, y0)
        self.mouse("mousePressed", x0, y0, pressed=True, clicks=1)
        for k in range(1, steps + 1):
            self.mouse("mouseMoved", x0 + (x1 - x0) * k / steps, y0 + (y1 - y0) * k / steps, pressed=True)
        self.mouse("mouseReleased", x1, y1, clicks=1)

    def screenshot(self, path: str | Path) -> Path:
        data = self.call("Page.captureScreenshot", format="png", captureBeyondViewport=False)["data"]
        Path(path).write_bytes(base64.b64decode(data))
        return Path(path)


class Browser:
    """A headless Chromium process with its own profile; tabs opened with :meth:`open`."""

    def __init__(self, proc: subprocess.Popen, profile: str, port: int, ws_path: str):
        self.proc, self.profile, self.port = proc, profile, port
        self.session = _Session(f"ws://127.0.0.1:{port}{ws_path}")
        self.tabs: list[Tab] = []

    @classmethod
    def launch(cls, download_dir: str | Path | None = None, width: int = 1400, height: int = 1100,
               extra_args: tuple[str, ...] = (), preexec_fn: Callable[[], None] | None = None) -> Browser:
        """Start Chromium (``preexec_fn``: run in its process before it starts, e.g. to lower its priority; its
        child processes inherit the scheduling policy and CPU affinity)."""
        if CHROMIUM is None:
            raise CdpError("chromium is not installed")
        profile = tempfile.mkdtemp(prefix="virtualaxis-chromium-")
        proc = subprocess.Popen(
            [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             "--no-first-run", "--no-default-browser-check", "--disable-extensions", "--mute-audio",
             "--remote-debugging-port=0", "--remote-debugging-address=127.0.0.1", f"--user-data-dir={profile}",
             f"--window-size={width},{height}", *extra_args, "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=preexec_fn)
        port_file = Path(profile) / "DevToolsActivePort"
        end = time.monotonic() + 60
        while time.monotonic() < end and not (port_file.exists() and len(port_file.read_text().split()) >= 2):
            if proc.poll() is not None:
                raise CdpError(f"chromium exited with {proc.returncode}")
            time.sleep(0.1)
        lines = port_file.read_text().split()
        b = cls(proc, profile, int(lines[0]), lines[1])
        if download_dir is not None:
            b.session.call("Browser.setDownloadBehavior", behavior="allow", downloadPath=str(download_dir),
                           eventsEnabled=True)
        return b

    def open(self, url: str, new_window: bool = False) -> Tab:
        target = self.session.call("Target.createTarget", url=url, newWindow=new_window)["targetId"]
        tab = Tab(f"ws://127.0.0.1:{self.port}/devtools/page/{target}")
        self.tabs.append(tab)
        return tab

    def close(self) -> None:
        for t in self.tabs:
            try:
                t.close()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        try:
            self.session.close()
        except Exception:  # noqa: BLE001
            pass
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def wait_for_file(folder: str | Path, suffix: str, timeout_s: float = 20.0) -> Path:
    """The first complete file ending in ``suffix`` that appears in ``folder``."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        done = [p for p in Path(folder).iterdir() if p.name.endswith(suffix)]
        if done:
            return done[0]
        time.sleep(0.1)
    raise CdpError(f"no *{suffix} in {folder} within {timeout_s} s: {os.listdir(folder)}")
