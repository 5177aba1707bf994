"""Screenshots of the web viewer from headless Chromium (Debian's /usr/bin/chromium via Playwright).

    python -m tools.viewer_screenshot http://127.0.0.1:8080 out/viewer/shot.png --every 5 --until-gone

takes a screenshot after the scene has loaded; with ``--every S`` it keeps overwriting it every S seconds
(and keeps numbered copies with ``--keep``) until ``--duration`` is over or, with ``--until-gone``, the
viewer stops answering: the file then shows the last state of a run. Exit 1 if the page logged errors.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
import urllib.request
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
# Software WebGL (SwiftShader through ANGLE): headless Chromium without a GPU needs the last two for WebGL.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
VIEWPORT = {"width": 1280, "height": 800}


def reachable(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=2.0):
            return True
    except OSError:
        return False


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="screenshot the sigmaslam viewer page")
    ap.add_argument("url", nargs="?", default="http://127.0.0.1:8080")
    ap.add_argument("out", nargs="?", default="out/viewer/screenshot.png")
    ap.add_argument("--wait", type=float, default=8.0, help="seconds after loading before the first shot [s]")
    ap.add_argument("--every", type=float, default=0.0, help="repeat every S seconds (0: one shot) [s]")
    ap.add_argument("--duration", type=float, default=3600.0, help="stop repeating after this long [s]")
    ap.add_argument("--until-gone", action="store_true", help="stop when the viewer no longer answers")
    ap.add_argument("--keep", action="store_true", help="also keep numbered copies OUT-0001.png, ...")
    ap.add_argument("--wait-up", type=float, default=60.0, help="wait this long for the viewer to answer [s]")
    args = ap.parse_args(argv)
    deadline = time.monotonic() + args.wait_up
    while not reachable(args.url):
        if time.monotonic() > deadline:
            print(f"{args.url} does not answer", file=sys.stderr)
            return 2
        time.sleep(1.0)
    from playwright.sync_api import sync_playwright

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    errors: list[str] = []
    t0 = time.monotonic()
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport=VIEWPORT)
            page.on("console", lambda msg: msg.type == "error" and errors.append(msg.text))
            page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
            page.goto(args.url)
            page.wait_for_timeout(args.wait * 1000)
            n = 0
            while True:
                if n and args.until_gone and not reachable(args.url):
                    break  # the viewer went away: keep the last screenshot of the live page
                tmp = out.with_suffix(".tmp.png")
                page.screenshot(path=str(tmp))
                tmp.replace(out)  # readers never see a half-written file
                n += 1
                if args.keep:
                    shutil.copy(out, out.with_name(f"{out.stem}-{n:04d}.png"))
                if args.every <= 0 or time.monotonic() - t0 > args.duration:
                    break
                time.sleep(args.every)
        finally:
            browser.close()
    print(f"wrote {out} ({n} screenshots)", flush=True)
    for e in errors:
        print(f"page error: {e}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
