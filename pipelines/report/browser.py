"""Open a report in headless Chromium and read back whether every picture decoded.

The page's inline script (``html.IMAGE_CHECK_SCRIPT``) writes ``data-images-loaded``,
``data-images-total`` and ``data-images-missing`` onto ``<body>`` after the load event; ``--dump-dom``
prints the DOM once the virtual time budget has run out, so those attributes are in the dump. The
browser runs with a throw-away profile, no network services and no GPU.
"""

from __future__ import annotations

import html
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from relightanyone.errors import DependencyError, RelightAnyoneError

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
INSTALL_HINT = "install it with `apt-get install chromium` (Debian/Ubuntu) or put chromium on PATH"
QUIET_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


class BrowserUnavailable(DependencyError):
    """No Chromium executable was found; the message says how to install one."""


class BrowserError(RelightAnyoneError, RuntimeError):
    """Chromium ran but did not check the page or write the screenshot; the message says what it printed."""


@dataclass
class BrowserCheck:
    """What the browser saw: ``loaded`` of ``total`` images decoded, the ``missing`` ones' URLs, the
    ``sections`` (ids of ``<section>`` elements) and the dumped DOM."""

    loaded: int
    total: int
    missing: list[str]
    sections: list[str]
    dom: str

    @property
    def ok(self) -> bool:
        return self.total == self.loaded and not self.missing


def find_chromium() -> Path:
    """The Chromium executable (``/usr/bin/chromium`` or one on PATH); raises ``BrowserUnavailable``."""
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return Path(found)
    raise BrowserUnavailable(f"no Chromium found (looked for {', '.join(CHROMIUM_NAMES)}); {INSTALL_HINT}")


def _run(chromium: Path, extra: list[str], url: str, timeout_s: float) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="report-chromium-") as profile:
        command = [str(chromium), *QUIET_FLAGS, f"--user-data-dir={profile}", *extra, url]
        return subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, check=False)


def _body_attribute(dom: str, name: str) -> str | None:
    body = re.search(r"<body\b[^>]*>", dom)
    if body is None:
        return None
    value = re.search(rf'\b{re.escape(name)}="([^"]*)"', body.group(0))
    return html.unescape(value.group(1)) if value else None


def check_in_browser(
    index_html: Path,
    chromium: Path | None = None,
    screenshot: Path | None = None,
    timeout_s: float = 120.0,
) -> BrowserCheck:
    """Load ``index_html`` in headless Chromium; count decoded images; optionally save a screenshot PNG.

    Raises ``BrowserUnavailable`` without a browser, ``BrowserError`` when the page script did not run.
    """
    chromium = chromium or find_chromium()
    url = Path(index_html).resolve().as_uri()
    result = _run(chromium, ["--virtual-time-budget=5000", "--dump-dom"], url, timeout_s)
    dom = result.stdout
    loaded, total = _body_attribute(dom, "data-images-loaded"), _body_attribute(dom, "data-images-total")
    if loaded is None or total is None:
        raise BrowserError(
            f"{index_html}: the page's image check did not run in {chromium} (exit {result.returncode}); "
            f"stderr: {result.stderr.strip()[-800:]}"
        )
    missing = (_body_attribute(dom, "data-images-missing") or "").split()
    sections = re.findall(r'<section\b[^>]*\bid="([^"]*)"', dom)
    if screenshot is not None:
        Path(screenshot).parent.mkdir(parents=True, exist_ok=True)
        shot = _run(
            chromium,
            [
                "--virtual-time-budget=5000",
                "--hide-scrollbars",
                "--window-size=1280,2400",
                f"--screenshot={Path(screenshot).resolve()}",
            ],
            url,
            timeout_s,
        )
        if not Path(screenshot).is_file():
            raise BrowserError(
                f"{chromium} wrote no screenshot to {screenshot}: {shot.stderr.strip()[-800:]}"
            )
    return BrowserCheck(int(loaded), int(total), missing, sections, dom)
