"""Screenshot of a rerun recording in rerun's web viewer, in headless Chromium (no GPU, no screen).

    python tools/rerun_screenshot.py RECORDING.rrd OUT.png [--wait 35] [--size 1600x900]

Needs Chromium (Debian: ``apt-get install chromium``) and the ``playwright`` Python package
(``pip install playwright``, in this or another environment; its own browser download is not
needed). Neither is a dependency of
granite-py. Serves the recording with ``rerun --serve-web`` (the ``rerun`` next to this Python),
opens the viewer with the WebGL renderer on ANGLE/EGL (software rendering; the default WebGPU
path and SwiftShader's WebGL lack limits the viewer needs), waits, and saves the page.
Made the README's picture: ``granite run assets/sequences/spiral --out runs/spiral-320
--rerun runs/spiral-320.rrd`` then this script.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

CHROMIUM_FLAGS = ["--no-sandbox", "--use-gl=angle", "--use-angle=gl-egl", "--ignore-gpu-blocklist"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--wait", type=float, default=45.0,
                        help="seconds to wait at least; then shots every 10 s until two agree")
    parser.add_argument("--max-wait", type=float, default=240.0, help="give up waiting after this")
    parser.add_argument("--size", default="1600x900", help="viewport WIDTHxHEIGHT")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    sibling = Path(sys.executable).with_name("rerun")
    parser.add_argument("--rerun-bin", default=str(sibling) if sibling.is_file() else shutil.which("rerun"),
                        help="the rerun command (default: next to this Python, else on PATH)")
    args = parser.parse_args()
    if not args.recording.is_file():
        sys.exit(f"rerun_screenshot: error: {args.recording}: recording not found")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sys.exit("rerun_screenshot: error: needs the playwright package (pip install playwright)")
    if not Path(args.chromium).is_file():
        sys.exit(f"rerun_screenshot: error: {args.chromium}: Chromium not found (apt-get install chromium)")
    width, height = (int(v) for v in args.size.split("x"))
    if not args.rerun_bin:
        sys.exit("rerun_screenshot: error: the rerun command was not found (pass --rerun-bin)")
    rerun = args.rerun_bin
    web, grpc = _free_port(), _free_port()
    server = subprocess.Popen([rerun, "--serve-web", str(args.recording), "--web-viewer-port", str(web),
                               "--port", str(grpc)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)  # the rerun wrapper starts a child server
    try:
        time.sleep(3.0)
        url = f"http://127.0.0.1:{web}/?renderer=webgl&url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy"
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=args.chromium, headless=True, args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            # Software rendering loads slowly (70-85 s seen for a 7 MB recording under load):
            # wait until two shots 10 s apart are identical.
            time.sleep(args.wait)
            shot, waited = page.screenshot(), args.wait
            while waited < args.max_wait:
                time.sleep(10.0)
                waited += 10.0
                previous, shot = shot, page.screenshot()
                if shot == previous:
                    break
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_bytes(shot)
            browser.close()
    finally:
        os.killpg(server.pid, signal.SIGTERM)  # the whole group, wrapper and server
        server.wait(timeout=10)
    print(f"screenshot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
