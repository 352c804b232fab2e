"""Draw docs/ui.png: the editor page on a fitted run with a material selected and recoloured.

    python docs/ui_figure.py runs/demo [--pixel X,Y] [--colour #RRGGBB] [-o docs/ui.png]

Starts the editor on a free loopback port, opens it in headless Chromium (Selenium), clicks the
pixel, sets the basecolor from the page's colour picker, waits for the refined frame and saves a
screenshot of the page.
"""

import argparse
import time
from pathlib import Path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run_dir")
    p.add_argument("--pixel", default="128,150", help="view pixel to click, X,Y")
    p.add_argument("--colour", default="#2f6bd8", help="basecolor to give the clicked material")
    p.add_argument("-o", "--output", default="docs/ui.png")
    args = p.parse_args()

    from vq_mitsuba.ui.browser import REFINED, click_pixel, headless_chromium, page_url, start_editor, \
        stop_editor, wait_page

    session, server = start_editor(args.run_dir)
    driver = headless_chromium(1000, 900)
    done = REFINED.format(spp=session.state()["refine_spp"])
    try:
        driver.get(page_url(server))
        wait_page(driver, done)
        x, y = (int(v) for v in args.pixel.split(","))
        click_pixel(driver, session.camera, x, y)
        wait_page(driver, "return document.getElementById('frame').dataset.selected")
        driver.execute_script(f"const c = document.getElementById('basecolor'); c.value = '{args.colour}'; "
                              "c.dispatchEvent(new Event('input')); c.dispatchEvent(new Event('change'));")
        wait_page(driver, "return document.querySelectorAll('#edits li').length === 1")
        time.sleep(0.5)
        wait_page(driver, done)
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(args.output)
        print(f"wrote {args.output}")
    finally:
        driver.quit()
        stop_editor(session, server)


if __name__ == "__main__":
    main()
