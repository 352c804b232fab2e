"""The editor driven from a headless browser, as the tests, the latency benchmark and the docs
figure drive it: a running editor on a free loopback port, Chromium through Selenium (Debian's
`chromium` and `chromium-driver`, `make chromium`), waiting for the page, clicking a view pixel."""

from __future__ import annotations

import shutil
import threading
import time
from pathlib import Path

from vq_mitsuba.ui.server import make_server
from vq_mitsuba.ui.session import EditorSession

# The view has drawn its refined frame (at least `spp` samples) and shows it.
REFINED = "const i = document.getElementById('frame'); return +i.dataset.spp >= {spp} && i.complete"


def start_editor(run_dir: str | Path, **session_options):
    """(session, server): an editor of RUN_DIR rendering and serving on 127.0.0.1, any free port."""
    session = EditorSession(run_dir, **session_options)
    server = make_server(session, port=0)
    session.start()
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return session, server


def stop_editor(session: EditorSession, server) -> None:
    server.shutdown()
    server.server_close()
    session.stop()


def page_url(server) -> str:
    host, port = server.server_address[:2]
    return f"http://{host}:{port}/"


def headless_chromium(width: int = 1200, height: int = 900):
    """A Selenium driver of headless Chromium at one device pixel per CSS pixel; raises when
    Chromium, chromedriver or selenium is missing or Chromium cannot start."""
    from selenium import webdriver

    chromium, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if not chromium or not driver_path:
        raise RuntimeError("Chromium or chromedriver is not installed (make chromium)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", "--force-device-scale-factor=1"):
        opts.add_argument(arg)
    return webdriver.Chrome(options=opts, service=webdriver.ChromeService(executable_path=driver_path))


def wait_page(driver, script: str, timeout: float = 120.0, poll: float = 0.1):
    """The first truthy value of the page script `script`, polled until `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(script)
        if value:
            return value
        time.sleep(poll)
    raise TimeoutError(f"the page never reached: {script}")


def click_pixel(driver, camera, x: int, y: int) -> None:
    """Click the centre of pixel (x, y) of the view image (drawn at any integer scale)."""
    from selenium.webdriver import ActionChains

    img = driver.find_element("id", "frame")
    scale = img.size["width"] / camera.width
    ActionChains(driver).move_to_element_with_offset(
        img, int((x + 0.5) * scale - img.size["width"] / 2), int((y + 0.5) * scale - img.size["height"] / 2)
    ).click().perform()
