"""Save a screenshot of a page of ``cfbci view`` once it shows a session at a given step.

Headless Chromium (Debian's ``chromium`` and ``chromium-driver``) driven by Selenium, a
fresh profile, the viewport set exactly (CSS pixels, times ``--scale``). The page is opened
with the view's access token: the one in the address if it has one, else ``--token``, else
``$CFBCI_VIEW_TOKEN``. To make the README's ``docs/operator-view.png`` again (a live
session on ``s4.mat``)::

    export CFBCI_VIEW_TOKEN=$(python3 -c 'import secrets; print(secrets.token_urlsafe(32))')
    cfbci serve --listen tcp/127.0.0.1:7447 &
    cfbci view --connect tcp/127.0.0.1:7447 --port 8080 &
    cfbci source --session s4 --dataset ../shared/datasets/errp-features-s4/s4.mat \\
        --seed 0 --steps 300 --interval 0.1 --connect tcp/127.0.0.1:7447 &
    .venv/bin/python tools/view_screenshot.py 'http://127.0.0.1:8080/?session=s4' \\
        docs/operator-view.png --step 240
"""

from __future__ import annotations

import argparse
import os
import tempfile
import urllib.parse
from pathlib import Path

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.support.ui import WebDriverWait

from cfbci.view import TOKEN_ENV
from cfbci.view.chromium import headless_options


def with_token(url: str, token: str | None) -> str:
    """``url`` with ``token=`` in its query, unless it has one or ``token`` is None."""
    parts = urllib.parse.urlsplit(url)
    query = urllib.parse.parse_qsl(parts.query)
    if token is None or any(name == "token" for name, _ in query):
        return url
    return parts._replace(query=urllib.parse.urlencode([*query, ("token", token)])).geturl()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("url", help="page of cfbci view, e.g. http://127.0.0.1:8080/?session=s4")
    parser.add_argument("out", type=Path, help="PNG file to write")
    parser.add_argument("--step", type=int, default=1, help="wait until this step is shown")
    parser.add_argument("--size", type=int, nargs=2, default=(1440, 880), metavar=("W", "H"),
                        help="viewport, CSS pixels (default 1440 880)")
    parser.add_argument("--scale", type=float, default=1.5, help="device pixel ratio")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds to wait")
    parser.add_argument("--token", default=os.environ.get(TOKEN_ENV),
                        help=f"the view's access token (default: ${TOKEN_ENV}); not needed if "
                        "the URL has one")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as profile:
        options = headless_options("/usr/bin/chromium", profile)
        driver = webdriver.Chrome(options=options, service=Service("/usr/bin/chromedriver"))
        try:
            driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
                "width": args.size[0], "height": args.size[1],
                "deviceScaleFactor": args.scale, "mobile": False,
            })
            driver.get(with_token(args.url, args.token))
            shown = "return Number(document.getElementById('view').dataset.step) || 0"
            WebDriverWait(driver, args.timeout, poll_frequency=0.05).until(
                lambda d: d.execute_script(shown) >= args.step
            )
            driver.save_screenshot(str(args.out))
        finally:
            driver.quit()
    print(f"{args.out}: {args.url} at step {args.step} or later")


if __name__ == "__main__":
    main()
