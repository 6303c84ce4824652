"""Headless Chromium for the viewer tests (Debian's ``chromium`` + ``chromium-driver``, driven by selenium;
the launcher is ``scripts/viewer_screenshot.py``'s). ``make setup`` installs both where it can; where they
are missing the tests that need them skip, saying so."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from scripts.viewer_screenshot import chromium_paths, open_chromium, viewer_value

__all__ = ["headless_chromium", "screenshot", "viewer_value", "CHROMIUM_MISSING"]

CHROMIUM_MISSING = None if chromium_paths() else (
    "Chromium or chromedriver is not installed (Debian: apt-get install chromium chromium-driver; "
    "`make setup` installs them where it has root or sudo)")


def headless_chromium(width: int = 1200, height: int = 760):
    """A selenium WebDriver of a headless Chromium with software WebGL; skips the test without one."""
    if CHROMIUM_MISSING:
        pytest.skip(CHROMIUM_MISSING)
    pytest.importorskip("selenium", reason="selenium is not installed (it is in the `test` extra: make setup)")
    return open_chromium(width, height)


def screenshot(driver) -> np.ndarray:
    """The page as an ``[H, W, 3]`` uint8 RGB array."""
    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))
