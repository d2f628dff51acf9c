"""Screenshot of the Rerun web viewer showing a run of the paper scenario, in headless Chromium.

    .venv/bin/pip install -e '.[docs]'   # playwright (it drives Debian's chromium)
    .venv/bin/python docs/take_screenshot.py [--run RESULTS_FOLDER] [--out docs/figures/viewer.png]

Without --run it first runs `phalanx up configs/scenarios/paper_wedge.toml` (recording on).
Then it serves the recording with `phalanx view --web` (bound to 127.0.0.1), opens the
viewer in headless Chromium (Debian's `chromium` package, software WebGL) and takes the
screenshot once the viewer has loaded its WebAssembly bundle and the recording.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from urllib.parse import quote

from phalanx.wire.transport import free_tcp_port

REPO = Path(__file__).resolve().parent.parent
# What this machine's closed network needs (no background fetches), plus software WebGL.
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--disable-quic", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--hide-scrollbars",
]  # fmt: skip


def run_scenario(out: Path) -> None:
    scenario = REPO / "configs" / "scenarios" / "paper_wedge.toml"
    subprocess.run(
        [sys.executable, "-m", "phalanx", "up", str(scenario), "--out", str(out)], check=True
    )


def wait_http(url: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2):  # noqa: S310 - http, loopback
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def screenshot(recording: Path, target: Path, *, wait_s: float, size: tuple[int, int]) -> None:
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or "/usr/bin/chromium"
    grpc, web = free_tcp_port(), free_tcp_port()
    viewer = subprocess.Popen(
        [sys.executable, "-m", "phalanx", "view", "--web", "--port", str(grpc),
         "--web-port", str(web), str(recording)],
    )  # fmt: skip
    url = f"http://127.0.0.1:{web}/?url={quote(f'rerun+http://127.0.0.1:{grpc}/proxy', safe='')}"
    try:
        wait_http(f"http://127.0.0.1:{web}/", 60.0)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": size[0], "height": size[1]})
            page.goto(url, wait_until="load", timeout=120_000)
            page.wait_for_selector("canvas", timeout=120_000)
            page.wait_for_timeout(1000 * wait_s)  # the recording streams in, first frames
            target.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(target))
            browser.close()
        print(f"wrote {target}")
    finally:
        viewer.terminate()
        try:
            viewer.wait(10)
        except subprocess.TimeoutExpired:
            viewer.kill()
            viewer.wait(5)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--run", type=Path, help="a results folder with run.rrd")
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "figures" / "viewer.png")
    parser.add_argument("--wait", type=float, default=60.0, help="seconds before the shot")
    args = parser.parse_args()
    run = args.run
    if run is None:
        run = Path(tempfile.mkdtemp(prefix="phalanx-run-"))
        run_scenario(run)
    screenshot(run / "run.rrd", args.out, wait_s=args.wait, size=(1600, 1000))


if __name__ == "__main__":
    main()
