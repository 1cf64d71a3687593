"""A real headless Chromium for tests: Debian's ``chromium`` and ``chromium-driver`` driven by Selenium.

No browser is downloaded: the system binaries are used (``.ci/run`` installs them with apt-get), and
name resolution sends every host but 127.0.0.1 nowhere, so a page that tried to load something from
the internet shows up as a failed request to another origin in :func:`network`.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = os.environ.get("MAXFS_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = os.environ.get("MAXFS_CHROMEDRIVER") or shutil.which("chromedriver") or "/usr/bin/chromedriver"
FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
]


def require_browser() -> None:
    """Skip without Chromium and chromedriver, unless ``MAXFS_REQUIRE_BROWSER=1`` (CI), which fails."""
    missing = [p for p in (CHROMIUM, CHROMEDRIVER) if not Path(p).exists()]
    if not missing:
        return
    msg = f"{', '.join(missing)} not found: apt-get install chromium chromium-driver"
    if os.environ.get("MAXFS_REQUIRE_BROWSER") == "1":
        pytest.fail(msg)
    pytest.skip(msg)


def start_chromium(width: int = 1280, height: int = 1000) -> Any:
    """A headless Chromium with a fresh profile that records its network events."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for flag in FLAGS:
        opts.add_argument(flag)
    profile = tempfile.mkdtemp(prefix="maxfs-chromium-")
    opts.add_argument(f"--user-data-dir={profile}")
    opts.add_argument(f"--window-size={width},{height}")
    opts.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    driver = webdriver.Chrome(options=opts, service=Service(CHROMEDRIVER))
    driver.maxfs_profile = profile
    return driver


def stop_chromium(driver: Any) -> None:
    try:
        driver.quit()
    finally:
        shutil.rmtree(driver.maxfs_profile, ignore_errors=True)


@dataclass
class Request:
    url: str
    status: int | None = None
    failed: str | None = None
    blocked: str | None = None  # why the browser did not send it (e.g. "csp")
    headers: dict[str, str] = field(default_factory=dict)


def network(driver: Any) -> list[Request]:
    """Every request the browser made since the last call, with its status or failure."""
    by_id: dict[str, Request] = {}
    for entry in driver.get_log("performance"):
        msg = json.loads(entry["message"])["message"]
        params = msg.get("params", {})
        rid = params.get("requestId")
        if msg["method"] == "Network.requestWillBeSent":
            req = params["request"]
            if req["url"].startswith(("chrome:", "chrome-untrusted:", "devtools:")):
                continue  # the browser's own pages (the first blank tab), not the network
            by_id[rid] = Request(req["url"], headers=req.get("headers", {}))
        elif msg["method"] == "Network.responseReceived" and rid in by_id:
            by_id[rid].status = params["response"]["status"]
        elif msg["method"] == "Network.loadingFailed" and rid in by_id:
            by_id[rid].failed = params.get("errorText", "failed")
            by_id[rid].blocked = params.get("blockedReason")
    return list(by_id.values())


def screenshot(driver: Any, path: Path) -> Path:
    """A PNG of the whole page (not only the window)."""
    import base64

    dims = driver.execute_cdp_cmd("Page.getLayoutMetrics", {})["cssContentSize"]
    shot = driver.execute_cdp_cmd(
        "Page.captureScreenshot",
        {
            "format": "png",
            "captureBeyondViewport": True,
            "clip": {"x": 0, "y": 0, "width": dims["width"], "height": dims["height"], "scale": 1},
        },
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(base64.b64decode(shot["data"]))
    return path
