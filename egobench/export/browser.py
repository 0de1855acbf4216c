"""The viewer page in a real browser: headless Chromium (the system's) driven by playwright.

Used by the browser test and by `egobench view --screenshot`. The browser is the distribution's
``chromium`` (``EGOBENCH_CHROMIUM`` names another executable); playwright only drives it, so nothing is
downloaded. WebGL runs on Chromium's software rasterizer (SwiftShader) where there is no GPU.
"""

from __future__ import annotations

import base64
import os
import shutil
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

#: where the browser is looked for, in order (EGOBENCH_CHROMIUM first)
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
#: software WebGL in a headless browser: SwiftShader, allowed explicitly
CHROMIUM_ARGS = ("--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist")
#: how long the page may take to load its data and draw the first frame, ms
READY_TIMEOUT_MS = 120_000


def chromium_executable() -> str | None:
    """The Chromium the page is opened in (EGOBENCH_CHROMIUM, else the first of CHROMIUM_NAMES on PATH), or None."""
    named = os.environ.get("EGOBENCH_CHROMIUM")
    if named:
        return named if Path(named).is_file() else None
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


def browser_missing() -> str | None:
    """Why no page can be opened here (no playwright, no Chromium), or None."""
    try:
        import playwright.sync_api  # noqa: F401  (optional: the test extra)
    except ImportError:
        return "playwright is not installed (pip install playwright; it drives the system's chromium)"
    if chromium_executable() is None:
        return f"no Chromium found ({', '.join(CHROMIUM_NAMES)} on PATH, or EGOBENCH_CHROMIUM)"
    return None


@contextmanager
def open_page(path, width: int = 1400, height: int = 900):
    """The page at ``path`` open in headless Chromium, ready (its first frame drawn) -> (page, requests): every
    request the page made is appended to ``requests`` (URLs)."""
    from playwright.sync_api import sync_playwright  # playwright: only where a page is opened

    missing = browser_missing()
    if missing:
        raise RuntimeError(f"view: cannot open the page in a browser: {missing}")
    url = Path(path).resolve().as_uri()
    requests: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_executable(), args=list(CHROMIUM_ARGS))
        try:
            page = browser.new_page(viewport={"width": width, "height": height}, device_scale_factor=1)
            page.on("request", lambda r: requests.append(r.url))
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            try:
                page.wait_for_function("() => window.egobench && window.egobench.ready", timeout=READY_TIMEOUT_MS)
            except Exception as exc:
                raise RuntimeError(f"{path}: the page did not draw its first frame: {errors or exc}") from exc
            yield page, requests
        finally:
            browser.close()


def canvas_pixels(page) -> np.ndarray:
    """The render canvas as drawn, [H, W, 3] float in [0, 1] (its PNG, 8 bits)."""
    url = page.evaluate("() => window.egobench.renderPNG()")
    png = base64.b64decode(url.split(",", 1)[1])
    bgr = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0


def page_screenshot(path, out, width: int = 960, height: int = 360) -> None:
    """A screenshot of the whole page at its first held-out camera into ``out`` (PNG; the page's full height)."""
    with open_page(path, width, height) as (page, _requests):
        page.screenshot(path=str(out), full_page=True)
