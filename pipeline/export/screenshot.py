"""A PNG of a page as headless Chromium (Debian's `chromium`) draws it after `wait_s` seconds of real time.

    python -m pipeline.export.screenshot http://127.0.0.1:8080 docs/img/view_far_jump.png --wait 20

For the README's picture of `adamimic view`: the viewer's scene arrives over its websocket after the page has
loaded, so Chromium's own `--screenshot` (taken at load) shows an empty canvas. This drives Chromium over its
DevTools protocol instead: open the page, wait, capture. Software WebGL (SwiftShader), no display needed.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path


def _browser() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return name
    raise FileNotFoundError("no Chromium on PATH (Debian: apt-get install chromium)")


async def _capture(ws_url: str, url: str, wait_s: float, width: int, height: int) -> bytes:
    import websockets

    async with websockets.connect(ws_url, max_size=64 * 2**20) as ws:
        counter = 0

        async def call(method: str, **params) -> dict:
            nonlocal counter
            counter += 1
            await ws.send(json.dumps({"id": counter, "method": method, "params": params}))
            while True:
                reply = json.loads(await ws.recv())
                if reply.get("id") == counter:
                    return reply.get("result", {})

        await call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
        await call("Page.navigate", url=url)
        await asyncio.sleep(wait_s)
        return base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])


def screenshot(url: str, out: str | Path, wait_s: float = 20.0, width: int = 1280, height: int = 720,
               port: int = 9333) -> Path:
    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="adamimic-chromium-") as profile:
        browser = subprocess.Popen([_browser(), "--headless=new", "--no-sandbox", "--use-gl=swiftshader",
                                    "--enable-unsafe-swiftshader", "--hide-scrollbars", f"--user-data-dir={profile}",
                                    f"--remote-debugging-port={port}", f"--window-size={width},{height}", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 30
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=2) as reply:
                        pages = [p for p in json.loads(reply.read()) if p.get("type") == "page"]
                    if pages:
                        break
                except OSError:
                    pass
                if time.monotonic() > deadline:
                    raise TimeoutError("Chromium's DevTools endpoint did not answer within 30 s")
                time.sleep(0.3)
            png = asyncio.run(_capture(pages[0]["webSocketDebuggerUrl"], url, wait_s, width, height))
        finally:
            browser.terminate()
            browser.wait(timeout=20)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(png)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("url")
    parser.add_argument("out", type=Path)
    parser.add_argument("--wait", type=float, default=20.0, help="seconds between opening the page and the capture")
    args = parser.parse_args()
    print(screenshot(args.url, args.out, args.wait))


if __name__ == "__main__":
    main()
