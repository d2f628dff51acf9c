"""Screenshot of the Rerun web viewer showing a run of the paper scenario, in headless Chromium.

    .venv/bin/python docs/take_screenshot.py [--run RESULTS_FOLDER] [--out docs/figures/viewer.png]

Without --run it first runs `phalanx up configs/scenarios/paper_wedge.toml` (recording on).
Then it serves the recording with `phalanx view --web` (bound to 127.0.0.1), opens the
viewer in headless Chromium (/usr/bin/chromium, software rendering) and, once the viewer
has had time to load the WebAssembly bundle and the recording, takes the screenshot over
the Chrome DevTools protocol. Needs Debian's `chromium` package.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from urllib.parse import quote, urlparse

REPO = Path(__file__).resolve().parent.parent
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars",
]  # fmt: skip


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class DevTools:
    """The smallest Chrome DevTools protocol client: one page, text frames, stdlib only."""

    def __init__(self, ws_url: str) -> None:
        url = urlparse(ws_url)
        self.sock = socket.create_connection((url.hostname, url.port), timeout=60)
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET {url.path} HTTP/1.1\r\nHost: {url.hostname}:{url.port}\r\n"
            "Upgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        )
        self.sock.sendall(request.encode())
        response = b""
        while b"\r\n\r\n" not in response:
            response += self.sock.recv(4096)
        if b" 101 " not in response.split(b"\r\n", 1)[0]:
            raise RuntimeError(f"websocket upgrade refused: {response[:200]!r}")
        self.next_id = 0

    def _send(self, text: str) -> None:
        payload = text.encode()
        header = bytearray([0x81])  # FIN, text frame
        n = len(payload)
        if n < 126:
            header.append(0x80 | n)
        elif n < 1 << 16:
            header += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            header += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        self.sock.sendall(
            bytes(header) + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        )

    def _recv_exact(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise RuntimeError("devtools connection closed")
            data += chunk
        return data

    def _recv(self) -> str:
        message = b""
        while True:
            first, second = self._recv_exact(2)
            n = second & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._recv_exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._recv_exact(8))[0]
            message += self._recv_exact(n)
            if first & 0x80:
                return message.decode()

    def call(self, method: str, **params: object) -> dict[str, object]:
        """Send a command; return its result (events in between are skipped)."""
        self.next_id += 1
        self._send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self._recv())
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                result: dict[str, object] = reply.get("result", {})
                return result


def run_scenario(out: Path) -> None:
    scenario = REPO / "configs" / "scenarios" / "paper_wedge.toml"
    subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(scenario), "--out", str(out)], check=True
    )


def screenshot(recording: Path, target: Path, *, wait_s: float, size: tuple[int, int]) -> None:
    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    grpc, web, debug = free_port(), free_port(), free_port()
    viewer = subprocess.Popen(
        [sys.executable, "-m", "phalanx", "view", "--web", "--port", str(grpc),
         "--web-port", str(web), str(recording)],
    )  # fmt: skip
    profile = tempfile.mkdtemp(prefix="phalanx-chromium-")
    url = f"http://127.0.0.1:{web}/?url={quote(f'rerun+http://127.0.0.1:{grpc}/proxy', safe='')}"
    browser = None
    try:
        time.sleep(3.0)  # the viewer's web server comes up
        browser = subprocess.Popen(
            [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             f"--remote-debugging-port={debug}", f"--window-size={size[0]},{size[1]}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        pages = []
        for _ in range(100):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{debug}/json/list") as r:
                    pages = [p for p in json.load(r) if p.get("type") == "page"]
                if pages:
                    break
            except OSError:
                pass
            time.sleep(0.2)
        if not pages:
            raise RuntimeError("chromium's devtools never answered")
        tools = DevTools(pages[0]["webSocketDebuggerUrl"])
        tools.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1],
                   deviceScaleFactor=1, mobile=False)  # fmt: skip
        time.sleep(wait_s)  # WebAssembly bundle, recording, software-rendered first frames
        shot = tools.call("Page.captureScreenshot", format="png")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(base64.b64decode(str(shot["data"])))
        print(f"wrote {target}")
    finally:
        for process in (browser, viewer):
            if process is not None:
                process.terminate()
                try:
                    process.wait(10)
                except subprocess.TimeoutExpired:
                    process.kill()
        shutil.rmtree(profile, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--run", type=Path, help="a results folder with run.rrd")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "figures" / "viewer.png")
    parser.add_argument("--wait", type=float, default=40.0, help="seconds before the shot")
    args = parser.parse_args()
    run = args.run
    if run is None:
        run = Path(tempfile.mkdtemp(prefix="phalanx-run-"))
        run_scenario(run)
    screenshot(run / "run.rrd", args.out, wait_s=args.wait, size=(1600, 1000))


if __name__ == "__main__":
    main()
