"""Chromium for the browser tests: Debian's package (``make browser``), launched by path with Playwright.

No browser download is reachable here, so Playwright's own browsers are never used. WebGL runs on
SwiftShader (software) in headless Chromium without a GPU.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator
from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]


def chromium_path() -> Path | None:
    """Debian's chromium, else one on PATH, else None."""
    if CHROMIUM.is_file():
        return CHROMIUM
    found = shutil.which("chromium")
    return Path(found) if found else None


def launch(playwright, **kwargs):
    """A headless Chromium browser (Playwright) from :func:`chromium_path`."""
    path = chromium_path()
    if path is None:
        raise FileNotFoundError("chromium not found (run `make browser`: Debian's chromium package)")
    return playwright.chromium.launch(executable_path=str(path), args=ARGS, headless=True, **kwargs)


@contextlib.contextmanager
def served_app(app) -> Iterator[str]:
    """The ASGI ``app`` served by uvicorn in a thread on a free loopback port; yields its URL, and
    stops the server after the block."""
    import threading
    import time

    import uvicorn

    from flows.server import free_port

    port = free_port("127.0.0.1")
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(30)
