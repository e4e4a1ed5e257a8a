"""Re-take the docs' viewer picture (``docs/assets/viewer.png``): ``python -m march.play ...
viewer=viser`` on a checkpoint, opened in headless Chromium and captured.

    python scripts/capture_viewer.py STUDENT_CKPT [--out docs/assets/viewer.png] [--port 0]
        [--size 1400x900] [--settle 10] [--run 0.8] [--turn 110] [--tilt 90] [--zoom 1]
        [--chromium chromium] [play overrides ...]

Not part of march's install nor of CI: it needs a Chromium (Debian: ``apt-get install chromium``)
and talks to it over the DevTools protocol (``--remote-debugging-port``, through the
``websockets`` package viser already brings). What a reader would do, in order: wait for the
panel, ``settle`` seconds for the meshes, **Reset Environment**, ``run`` seconds of play,
**Pause** (the picture holds still: an untrained smoke student falls within a second or two),
a mouse drag of ``turn`` x ``tilt`` pixels and ``zoom`` wheel notches to orbit the camera onto
the plan, the **Rewards** tab. Headless Chromium draws WebGL in software (SwiftShader,
``--use-angle=swiftshader --enable-unsafe-swiftshader``), so viser's client shows its "Software
WebGL rendering detected" notice (viser ``BrowserWarning.tsx``: a Mantine notification that never
closes by itself); the script closes it with the notice's own close button and refuses to
capture while any notification is left (nothing is hidden by CSS). Overrides after the
checkpoint go to ``march.play`` (default ``compute=smoke``). It prints the picture's path and
size. One capture takes about a minute on 2 cores.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]

CLOSE_NOTICES = """(() => {
  const closes = [...document.querySelectorAll('.mantine-Notification-root button')];
  closes.forEach((b) => b.click());
  return closes.length;
})()"""
"""Clicks every notification's close button (viser's notices are Mantine notifications)."""

NOTICES_LEFT = "document.querySelectorAll('.mantine-Notification-root').length"

BUTTON = """((text) => {
  const b = [...document.querySelectorAll('button')].find((e) => e.textContent.trim() === text);
  if (!b) return null;
  const r = b.getBoundingClientRect();
  return r.width > 0 ? {x: r.x + r.width / 2, y: r.y + r.height / 2} : null;
})"""
"""Where a visible button of mjlab's panel is, by its text."""

REWARDS_TAB = """(() => {
  const tab = [...document.querySelectorAll('[role=tab]')]
    .find((t) => t.textContent.trim() === 'Rewards');
  if (!tab) return null;
  const r = tab.getBoundingClientRect();
  return {x: r.x + r.width / 2, y: r.y + r.height / 2, selected: tab.ariaSelected === 'true'};
})()"""
"""Where mjlab's Rewards tab is (viser's dock tabs answer pointer events, not ``click()``)."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(what: str, check: Any, timeout: float) -> object:
    deadline = time.time() + timeout
    while time.time() < deadline:
        got = check()
        if got:
            return got
        time.sleep(0.5)
    raise SystemExit(f"capture_viewer: {what} not ready after {timeout:.0f} s")


def _drain(proc: subprocess.Popen) -> None:
    assert proc.stdout is not None
    for line in proc.stdout:
        print(line.rstrip())


def _start_play(ckpt: str, port: int, overrides: list[str]) -> subprocess.Popen:
    args = [sys.executable, "-m", "march.play", f"student_ckpt={ckpt}", "viewer=viser"]
    args += [f"port={port}", *(overrides or ["compute=smoke"])]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        args, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    assert proc.stdout is not None
    for line in proc.stdout:  # the env builds, then play prints the viewer's address
        print(line.rstrip())
        if "mjlab's viewer at http://" in line:  # keep reading: a full pipe would stall play
            threading.Thread(target=_drain, args=(proc,), daemon=True).start()
            return proc
    raise SystemExit(f"capture_viewer: march.play ended (exit {proc.wait()}) before serving")


def _start_chromium(binary: str, size: tuple[int, int], profile: str) -> tuple[Any, int]:
    port = _free_port()
    args = [
        binary,
        "--headless=new",
        "--no-sandbox",  # root in a container
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--hide-scrollbars",
        f"--window-size={size[0]},{size[1]}",
        f"--remote-debugging-port={port}",
        f"--user-data-dir={profile}",
        "about:blank",
    ]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return proc, port


def _page_ws(port: int) -> str:
    def pages() -> str | None:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=2) as r:
                tabs = json.load(r)
        except OSError:
            return None
        return next((t["webSocketDebuggerUrl"] for t in tabs if t.get("type") == "page"), None)

    return str(_wait_for("Chromium's DevTools", pages, 60))


async def _capture(
    ws_url: str,
    url: str,
    size: tuple[int, int],
    settle: float,
    run: float,
    turn: float,
    tilt: float,
    zoom: int,
) -> bytes:
    import websockets

    async with websockets.connect(ws_url, max_size=2**28) as ws:
        counter = 0

        async def call(method: str, **params: object) -> dict:
            nonlocal counter
            counter += 1
            await ws.send(json.dumps({"id": counter, "method": method, "params": params}))
            while True:
                msg = json.loads(await ws.recv())
                if msg.get("id") == counter:
                    if "error" in msg:
                        raise SystemExit(f"capture_viewer: {method}: {msg['error']}")
                    return msg.get("result", {})

        async def js(expr: str) -> object:
            res = await call("Runtime.evaluate", expression=expr, returnByValue=True)
            return res.get("result", {}).get("value")

        await call(
            "Emulation.setDeviceMetricsOverride",
            width=size[0],
            height=size[1],
            deviceScaleFactor=1,
            mobile=False,
        )
        await call("Page.navigate", url=url)

        async def click(x: float, y: float) -> None:  # a reader's mouse click
            for kind in ("mousePressed", "mouseReleased"):
                await call(
                    "Input.dispatchMouseEvent", type=kind, x=x, y=y, button="left", clickCount=1
                )

        async def press(text: str) -> None:
            at = await js(f"{BUTTON}({json.dumps(text)})")
            if not at:
                raise SystemExit(f"capture_viewer: no {text!r} button in the viewer's panel")
            await click(at["x"], at["y"])

        for _ in range(120):  # the panel appears once the scene streams
            if await js(f"{BUTTON}('Reset Environment')"):
                break
            await asyncio.sleep(1.0)
        else:
            raise SystemExit("capture_viewer: the viewer's panel never appeared")
        await asyncio.sleep(settle)  # the meshes load
        await press("Reset Environment")  # a fresh episode: the robot on the start platform
        await asyncio.sleep(run)
        await press("Pause")  # the picture holds still while the panel is switched
        if turn or tilt:  # orbit the camera (a drag in the scene, as a reader would)
            x0, y0 = 0.35 * size[0], 0.45 * size[1]
            await call("Input.dispatchMouseEvent", type="mousePressed", x=x0, y=y0, button="left")
            for i in range(1, 21):
                await call(
                    "Input.dispatchMouseEvent",
                    type="mouseMoved",
                    x=x0 + turn * i / 20,
                    y=y0 + tilt * i / 20,
                    button="left",
                    buttons=1,
                )
                await asyncio.sleep(0.03)
            await call("Input.dispatchMouseEvent", type="mouseReleased", x=x0 + turn, y=y0 + tilt)
        for _ in range(abs(int(zoom))):  # mouse-wheel notches: out (> 0) or in (< 0)
            await call(
                "Input.dispatchMouseEvent",
                type="mouseWheel",
                x=0.35 * size[0],
                y=0.45 * size[1],
                deltaX=0,
                deltaY=100 if zoom > 0 else -100,
            )
            await asyncio.sleep(0.1)
        for _ in range(30):  # the Rewards tab: click until it is open
            tab = await js(REWARDS_TAB)
            if tab and tab["selected"]:
                break
            if tab:
                await click(tab["x"], tab["y"])
            await asyncio.sleep(1.0)
        else:
            raise SystemExit("capture_viewer: the viewer's Rewards tab did not open")
        await asyncio.sleep(3.0)  # the scene redrawn from the new camera
        closed = await js(CLOSE_NOTICES)
        await asyncio.sleep(1.5)  # the notification's exit transition
        left = await js(NOTICES_LEFT)
        print(f"[capture] closed {closed} notice(s); {left} left")
        if left:
            raise SystemExit(f"capture_viewer: {left} notification(s) still shown")
        shot = await call("Page.captureScreenshot", format="png")
        return base64.b64decode(shot["data"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ckpt", help="a student checkpoint (student/latest.pt of a run)")
    p.add_argument("--out", default=str(REPO / "docs" / "assets" / "viewer.png"))
    p.add_argument("--port", type=int, default=0, help="play's port (0: a free one)")
    p.add_argument("--size", default="1400x900", help="the browser window, WIDTHxHEIGHT pixels")
    p.add_argument("--settle", type=float, default=10.0, help="seconds for the scene to load")
    p.add_argument("--run", type=float, default=0.8, help="seconds played after the reset")
    p.add_argument("--turn", type=float, default=110.0, help="camera drag rightwards [pixels]")
    p.add_argument("--tilt", type=float, default=90.0, help="camera drag downwards [pixels]")
    p.add_argument("--zoom", type=int, default=1, help="mouse-wheel notches out (< 0: in)")
    p.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    args, overrides = p.parse_known_args(argv)
    if shutil.which(args.chromium) is None:
        raise SystemExit(f"capture_viewer: no Chromium at {args.chromium!r} (--chromium PATH)")
    try:
        size = tuple(int(v) for v in args.size.lower().split("x"))
        assert len(size) == 2 and min(size) > 0
    except (ValueError, AssertionError):
        raise SystemExit(f"capture_viewer: --size {args.size}: give WIDTHxHEIGHT") from None
    port = args.port or _free_port()
    play = _start_play(args.ckpt, port, overrides)
    try:
        with tempfile.TemporaryDirectory(prefix="capture_viewer_") as profile:
            browser, cdp_port = _start_chromium(args.chromium, size, profile)
            try:
                png = asyncio.run(
                    _capture(
                        _page_ws(cdp_port),
                        f"http://localhost:{port}",
                        size,
                        args.settle,
                        args.run,
                        args.turn,
                        args.tilt,
                        args.zoom,
                    )
                )
            finally:
                browser.terminate()
                browser.wait(timeout=30)
    finally:
        play.send_signal(signal.SIGINT)  # play closes the viewer and the env on Ctrl-C
        try:
            play.wait(timeout=120)
        except subprocess.TimeoutExpired:
            play.kill()
    out = Path(args.out)
    out.write_bytes(png)
    print(f"[capture] wrote {out} ({size[0]}x{size[1]}, {len(png)} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
