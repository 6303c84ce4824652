"""Screenshot a session's live viewer in headless Chromium (software WebGL), e.g. for the docs::

    python scripts/viewer_screenshot.py "http://127.0.0.1:8000/sessions/<id>/view?token=<token>" docs/viewer.png

It waits until the page shows a mesh (``--min-mesh-version``) and the trajectory, then saves the page.
Needs Debian's ``chromium`` and ``chromium-driver`` (``make setup`` installs them) and selenium (the
``test`` extra). The viewer tests use :func:`open_chromium` too.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["chromium_paths", "open_chromium", "viewer_value", "main"]


def chromium_paths() -> tuple[str, str] | None:
    """``(chromium binary, chromedriver)`` when both are installed, else ``None``."""
    binary = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    driver = shutil.which("chromedriver")
    return (binary, driver) if binary and driver else None


def open_chromium(width: int = 1200, height: int = 760) -> Any:
    """A selenium ``WebDriver`` of a headless Chromium with software WebGL (SwiftShader) and the browser
    console log kept. Raises ``RuntimeError`` when Chromium or its driver is missing."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    paths = chromium_paths()
    if paths is None:
        raise RuntimeError("Chromium or chromedriver is not installed (Debian: apt-get install chromium "
                           "chromium-driver; `make setup` installs them where it has root or sudo)")
    options = webdriver.ChromeOptions()
    options.binary_location = paths[0]
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", f"--window-size={width},{height}",
                "--hide-scrollbars", "--no-first-run", "--disable-extensions"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(paths[1]), options=options)


def viewer_value(driver: Any, key: str) -> str | None:
    """What the viewer page publishes in ``document.body.dataset[key]`` (``meshVersion``, ``meshVertices``,
    ``poses``, ``frameSeq``, ``state``, ``framesTracked``), or ``None``."""
    return driver.execute_script("return document.body.dataset[arguments[0]] || null;", key)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("url", help="the viewer link (with ?token=)")
    parser.add_argument("out", type=Path, help="PNG file to write")
    parser.add_argument("--min-mesh-version", type=int, default=1, help="wait for at least this map version")
    parser.add_argument("--settle-s", type=float, default=3.0, help="wait this long after the mesh loads")
    parser.add_argument("--timeout-s", type=float, default=300.0)
    parser.add_argument("--size", default="1400x820", help="window size WxH")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    driver = open_chromium(width, height)
    try:
        driver.get(args.url)
        deadline = time.monotonic() + args.timeout_s
        while int(viewer_value(driver, "meshVersion") or -1) < args.min_mesh_version:
            if time.monotonic() > deadline:
                print(f"no mesh of map version >= {args.min_mesh_version} after {args.timeout_s:.0f} s",
                      file=sys.stderr)
                return 1
            time.sleep(0.5)
        time.sleep(args.settle_s)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_bytes(driver.get_screenshot_as_png())
        print(f"wrote {args.out} (map version {viewer_value(driver, 'meshVersion')}, "
              f"{viewer_value(driver, 'meshVertices')} mesh vertices, {viewer_value(driver, 'poses')} poses)")
        return 0
    finally:
        driver.quit()


if __name__ == "__main__":
    sys.exit(main())
