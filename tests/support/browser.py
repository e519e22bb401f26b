"""Headless Chromium for the page tests: Debian's ``chromium`` and ``chromium-driver``
driven by selenium (the ``browser`` extra), WebGL on the CPU (SwiftShader), every host
name unresolvable so nothing can be fetched, and the browser's console kept.

:func:`browser_or_skip` returns a started driver, or skips the test saying what is
missing; with ``CNNPS_REQUIRE_BROWSER=1`` (``.ci/run`` installs all of it and sets it) a
missing piece fails the test instead, so CI cannot skip them unnoticed.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

CHROMIUM = ("chromium", "chromium-browser", "google-chrome")
DRIVER = ("chromedriver",)
FLAGS = (
    "--headless=new",
    "--no-sandbox",  # root in a container
    "--disable-dev-shm-usage",
    "--use-angle=swiftshader",  # WebGL without a GPU
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    '--host-resolver-rules=MAP * ~NOTFOUND',  # no host name resolves: nothing can be fetched
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--window-size=1280,1600",
)


def _which(names) -> str | None:
    for name in names:
        found = shutil.which(name) or (f"/usr/lib/chromium/{name}" if Path(f"/usr/lib/chromium/{name}").is_file()
                                       else None)
        if found:
            return found
    return None


def missing() -> str | None:
    """Why the browser tests cannot run here, or None."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install '.[browser]')"
    if _which(CHROMIUM) is None:
        return "Chromium is not installed (apt-get install chromium chromium-driver)"
    if _which(DRIVER) is None:
        return "chromedriver is not installed (apt-get install chromium-driver)"
    return None


def start_browser():
    """A headless Chromium (selenium WebDriver) with :data:`FLAGS` and the console log kept."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    os.environ.setdefault("SE_OFFLINE", "true")  # Selenium Manager: never download a driver
    options = webdriver.ChromeOptions()
    options.binary_location = _which(CHROMIUM)
    for flag in FLAGS:
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    return webdriver.Chrome(service=Service(executable_path=_which(DRIVER)), options=options)


def browser_or_skip():
    reason = missing()
    if reason and os.environ.get("CNNPS_REQUIRE_BROWSER") == "1":
        pytest.fail(f"browser test: {reason}, and CNNPS_REQUIRE_BROWSER=1")
    if reason:
        pytest.skip(f"browser test: {reason}")
    return start_browser()


def console_errors(driver) -> list[str]:
    """The console's SEVERE entries since the last call (errors and uncaught exceptions)."""
    return [f"{e['level']}: {e['message']}" for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def outside_requests(driver) -> list[str]:
    """What the page (or the frame the driver is in) asked for beyond itself: its resource
    entries that are not data: or blob: URLs, and every request the browser's network
    log saw since the last call that is not file:, data: or blob:."""
    import json

    names = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    found = [n for n in names if not n.startswith(("data:", "blob:"))]
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message.get("method") == "Network.requestWillBeSent":
            url = message["params"]["request"]["url"]
            if not url.startswith(("file:", "data:", "blob:")):
                found.append(url)
    return found


def screenshot(page: Path, out: Path, light=None, glossy: bool = False, width: int = 1280) -> None:
    """A picture of the whole of report page ``page`` (what docs/images/report_*.png
    are): the light set to ``light`` (a unit vector) and gloss on with ``glossy``."""
    import time

    driver = start_browser()
    try:
        driver.get(Path(page).resolve().as_uri())
        end = time.monotonic() + 60
        while not driver.execute_script("return window.cnnpsReport && window.cnnpsReport.ready"):
            if time.monotonic() > end:
                raise TimeoutError(f"{page}: the page did not get ready")
            time.sleep(0.1)
        if glossy:
            driver.find_element("id", "glossy").click()
        if light is not None:
            driver.execute_script("window.cnnpsReport.setLight(arguments[0])", list(light))
        driver.set_window_size(width, driver.execute_script("return document.documentElement.scrollHeight") + 140)
        time.sleep(1.0)
        driver.save_screenshot(str(out))
    finally:
        driver.quit()
