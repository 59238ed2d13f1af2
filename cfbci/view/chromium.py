"""Headless Chromium for the view's pages, driven by Selenium: the options that
``cfbci bench timing``, the browser tests and ``tools/view_screenshot.py`` share."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from selenium.webdriver import ChromeOptions

#: Headless, no sandbox (as root in a container), no GPU, and nothing the browser would
#: do on its own (updates, sync, first-run pages, scroll bars over the page).
HEADLESS_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
)


def headless_options(binary: str, profile: str | Path, *flags: str) -> ChromeOptions:
    """Selenium's ``ChromeOptions`` of headless Chromium (`HEADLESS_FLAGS`).

    Parameters
    ----------
    binary : str
        The Chromium executable.
    profile : str or Path
        Its user data folder (a fresh one: no state of another browser).
    *flags : str
        More command-line flags (a window size, host resolver rules).
    """
    from selenium import webdriver  # a development dependency, not the service's

    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for flag in (*HEADLESS_FLAGS, f"--user-data-dir={profile}", *flags):
        options.add_argument(flag)
    return options
