"""Screenshots of the HTML recordings in a headless Chromium: what a user's browser shows."""

import shutil
import subprocess
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")


def find_chromium() -> str | None:
    """The path of a Chromium-family browser on PATH, or None."""
    return next((path for path in map(shutil.which, CHROMIUM_NAMES) if path), None)


def screenshot(html: str | Path, png: str | Path, width: int = 800, height: int = 600, wait_ms: int = 15000) -> Path:
    """Opens `html` in headless Chromium and saves what it shows after `wait_ms` as `png`.

    SwiftShader gives the page's WebGL a software renderer (no GPU, no display needed).

    Raises:
        FileNotFoundError: no Chromium, or no `html` file.
        subprocess.CalledProcessError: the browser failed (its stderr is in the error).
    """
    browser = find_chromium()
    if browser is None:
        raise FileNotFoundError(f"no Chromium found (looked for {list(CHROMIUM_NAMES)}; Debian: apt-get install chromium)")
    html, png = Path(html).resolve(), Path(png)
    if not html.is_file():
        raise FileNotFoundError(f"no HTML file at {html}")
    png.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run([browser, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                    f"--window-size={width},{height}", f"--timeout={wait_ms}", f"--screenshot={png.resolve()}",
                    html.as_uri()], check=True, capture_output=True, timeout=wait_ms / 1000 + 120)
    return png
