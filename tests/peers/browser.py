"""Headless Chromium through Debian's chromedriver (Selenium), and ``companion view`` as a child process.

Nothing is downloaded at run time: Selenium is pointed at /usr/bin/chromedriver and /usr/bin/chromium
(Debian's ``chromium`` and ``chromium-driver``); :func:`browser_missing` says why a test must skip.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHROMIUM_CANDIDATES = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
CHROMEDRIVER_CANDIDATES = ("/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver")
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--window-size=1280,1000",
)


def _first(paths: tuple[str, ...]) -> str | None:
    return next((p for p in paths if os.access(p, os.X_OK)), None)


def browser_missing() -> str | None:
    """Why the browser tests cannot run here (None when they can)."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install '.[test]')"
    if _first(CHROMIUM_CANDIDATES) is None:
        return "no /usr/bin/chromium (Debian: apt-get install chromium chromium-driver; .ci/run does it)"
    if _first(CHROMEDRIVER_CANDIDATES) is None:
        return "no /usr/bin/chromedriver (Debian: apt-get install chromium-driver; .ci/run does it)"
    return None


class Browser:
    """A headless Chromium with a fresh profile; ``driver`` is the Selenium WebDriver."""

    def __init__(self, width: int = 1280, height: int = 1000, mobile: bool = False) -> None:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service as DriverService

        self._profile = tempfile.mkdtemp(prefix="companion-chromium-")
        options = webdriver.ChromeOptions()
        options.binary_location = _first(CHROMIUM_CANDIDATES)
        for flag in CHROMIUM_FLAGS:
            options.add_argument(flag)
        options.add_argument(f"--user-data-dir={self._profile}")
        options.add_argument(f"--window-size={width},{height}")
        if mobile:
            options.add_experimental_option("mobileEmulation", {"deviceMetrics": {"width": width, "height": height, "pixelRatio": 2.0}})
        service = DriverService(executable_path=_first(CHROMEDRIVER_CANDIDATES), log_output=subprocess.DEVNULL)
        self.driver = webdriver.Chrome(options=options, service=service)
        self.driver.set_page_load_timeout(20)

    def close(self) -> None:
        try:
            self.driver.quit()
        finally:
            shutil.rmtree(self._profile, ignore_errors=True)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ViewProcess:
    """``python -m companion view ...`` in a child process; :attr:`url` is the first URL it printed."""

    def __init__(self, *args: str, env: dict[str, str] | None = None, timeout_s: float = 60.0) -> None:
        cmd = [sys.executable, "-m", "companion", "view", "--port", "0", *args]
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, **(env or {})},
            cwd=tempfile.gettempdir(),
        )
        self.lines: list[str] = []
        self.url = self._wait_url(timeout_s)

    def _wait_url(self, timeout_s: float) -> str:
        import threading

        def read() -> None:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                self.lines.append(line.rstrip("\n"))

        threading.Thread(target=read, name="view-stdout", daemon=True).start()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in list(self.lines):
                m = re.search(r"companion view: open (\S+)", line)
                if m:
                    return m.group(1)
            if self.proc.poll() is not None:
                time.sleep(0.2)
                break
            time.sleep(0.05)
        self.stop()
        raise AssertionError("companion view did not print its URL:\n" + "\n".join(self.lines[-40:]))

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self) -> ViewProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def screenshot_png(driver, element_id: str) -> bytes:
    """The PNG of one element of the page."""
    return driver.find_element("id", element_id).screenshot_as_png


def save(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path
