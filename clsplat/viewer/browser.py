"""A headless Chromium pointed at a viewer, for tests and README screenshots: WebGL through
SwiftShader (no GPU needed), screenshots over the DevTools protocol (websockets, a viser dependency).

    with HeadlessChromium(viewer.url) as b:
        img = b.screenshot()          # [H, W, 3] uint8
"""
from __future__ import annotations

import base64
import json
import shutil
import socket
import subprocess
import tempfile
import urllib.request
from pathlib import Path

import numpy as np

__all__ = ["HeadlessChromium", "find_chromium"]


def find_chromium() -> str | None:
    """Path of Debian's ``chromium`` (or ``chromium-browser``), or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


class HeadlessChromium:
    """``chromium --headless`` showing ``url`` in a ``width`` x ``height`` window until closed."""

    def __init__(self, url: str, width: int = 1000, height: int = 640, binary: str | None = None) -> None:
        binary = binary or find_chromium()
        if binary is None:
            raise FileNotFoundError("chromium is not installed (apt-get install chromium)")
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        self.debug_port = s.getsockname()[1]
        s.close()
        # chromium's helper processes can still write into the profile after the main one exits:
        # removing it must not fail the caller (seen once in a full test run: "Default" not empty)
        self._profile = tempfile.TemporaryDirectory(prefix="clsplat-chromium-", ignore_cleanup_errors=True)
        self.proc = subprocess.Popen(
            [binary, "--headless=new", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
             "--enable-unsafe-swiftshader", "--hide-scrollbars", f"--window-size={width},{height}",
             f"--remote-debugging-port={self.debug_port}", f"--user-data-dir={self._profile.name}",
             "--no-first-run", url], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def screenshot(self, timeout: float = 60) -> np.ndarray:
        """[H, W, 3] uint8 screenshot of the page."""
        from websockets.sync.client import connect

        from ..io.images import read_image
        pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{self.debug_port}/json/list", timeout=timeout))
        ws = [p for p in pages if p["type"] == "page"][0]["webSocketDebuggerUrl"]
        with connect(ws, max_size=None, open_timeout=timeout) as c:
            c.send(json.dumps({"id": 1, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
            while True:
                m = json.loads(c.recv(timeout=timeout))
                if m.get("id") == 1:
                    break
        with tempfile.TemporaryDirectory() as d:
            f = Path(d) / "shot.png"
            f.write_bytes(base64.b64decode(m["result"]["data"]))
            return (read_image(f) * 255).round().astype(np.uint8)

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._profile.cleanup()

    def __enter__(self) -> "HeadlessChromium":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
