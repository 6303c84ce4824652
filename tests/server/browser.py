"""Headless Chromium for the viewer tests (Debian's ``chromium`` + ``chromium-driver``, driven by selenium).

``make setup`` installs both where it can (``scripts/bootstrap.sh``); where they are missing the tests that
need them skip, saying so.
"""

from __future__ import annotations

import io
import shutil

import numpy as np
import pytest
from PIL import Image

__all__ = ["headless_chromium", "screenshot", "CHROMIUM_MISSING"]

_CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
_DRIVER = shutil.which("chromedriver")
CHROMIUM_MISSING = None if _CHROMIUM and _DRIVER else (
    "Chromium or chromedriver is not installed (Debian: apt-get install chromium chromium-driver; "
    "`make setup` installs them where it has root or sudo)")


def headless_chromium(width: int = 1200, height: int = 760):
    """A selenium WebDriver of a headless Chromium with software WebGL (SwiftShader)."""
    if CHROMIUM_MISSING:
        pytest.skip(CHROMIUM_MISSING)
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (it is in the `test` extra: make setup)")
    options = webdriver.ChromeOptions()
    options.binary_location = _CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", f"--window-size={width},{height}",
                "--hide-scrollbars", "--no-first-run", "--disable-extensions"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(_DRIVER), options=options)


def screenshot(driver) -> np.ndarray:
    """The page as an ``[H, W, 3]`` uint8 RGB array."""
    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))
