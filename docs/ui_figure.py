"""Draw docs/ui.png: the editor page on a fitted run with a material selected and recoloured.

    python docs/ui_figure.py runs/demo [--pixel X,Y] [--colour #RRGGBB] [-o docs/ui.png]

Starts the editor on a free loopback port, opens it in headless Chromium (Selenium), clicks the
pixel, sets the basecolor from the page's colour picker, waits for the refined frame and saves a
screenshot of the page.
"""

import argparse
import shutil
import threading
import time
from pathlib import Path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir")
    p.add_argument("--pixel", default="128,150", help="view pixel to click, X,Y")
    p.add_argument("--colour", default="#2f6bd8", help="basecolor to give the clicked material")
    p.add_argument("-o", "--output", default="docs/ui.png")
    args = p.parse_args()

    from selenium import webdriver
    from selenium.webdriver import ActionChains

    from vq_mitsuba.ui.server import make_server
    from vq_mitsuba.ui.session import EditorSession

    session = EditorSession(args.run_dir)
    server = make_server(session, port=0)
    session.start()
    threading.Thread(target=server.serve_forever, daemon=True).start()
    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium")
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1000,900", "--force-device-scale-factor=1"):
        opts.add_argument(a)
    driver = webdriver.Chrome(options=opts, service=webdriver.ChromeService(executable_path=shutil.which("chromedriver")))
    refined = session.state()["refine_spp"]

    def wait(script):
        for _ in range(1200):
            if driver.execute_script(script):
                return
            time.sleep(0.1)
        raise SystemExit(f"the page never reached: {script}")

    done = f"const i = document.getElementById('frame'); return +i.dataset.spp >= {refined} && i.complete"
    try:
        host, port = server.server_address[:2]
        driver.get(f"http://{host}:{port}/")
        wait(done)
        x, y = (int(v) for v in args.pixel.split(","))
        img = driver.find_element("id", "frame")
        scale = img.size["width"] / session.camera.width
        ActionChains(driver).move_to_element_with_offset(
            img, int((x + 0.5) * scale - img.size["width"] / 2), int((y + 0.5) * scale - img.size["height"] / 2)).click().perform()
        wait("return document.getElementById('frame').dataset.selected")
        driver.execute_script(f"const c = document.getElementById('basecolor'); c.value = '{args.colour}'; "
                              "c.dispatchEvent(new Event('input')); c.dispatchEvent(new Event('change'));")
        wait("return document.querySelectorAll('#edits li').length === 1")
        time.sleep(0.5)
        wait(done)
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(args.output)
        print(f"wrote {args.output}")
    finally:
        driver.quit()
        server.shutdown()
        session.stop()


if __name__ == "__main__":
    main()
