"""Headless Chromium for the page tests: Debian's ``chromium`` and ``chromium-driver``
driven by selenium (the ``browser`` extra), WebGL on the CPU (SwiftShader), every host
name unresolvable so nothing can be fetched, and the browser's console kept.

:func:`browser_or_skip` returns a started driver, or skips the test saying what is
missing (``.ci/run`` installs all of it, so CI runs these tests).
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
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(executable_path=_which(DRIVER)), options=options)


def browser_or_skip():
    reason = missing()
    if reason:
        pytest.skip(f"browser test: {reason}")
    return start_browser()


def console_errors(driver) -> list[str]:
    """The console's SEVERE entries since the last call (errors and uncaught exceptions)."""
    return [f"{e['level']}: {e['message']}" for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def outside_requests(driver) -> list[str]:
    """The page's resource entries that are not its own data: or blob: URLs."""
    names = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    return [n for n in names if not n.startswith(("data:", "blob:"))]
