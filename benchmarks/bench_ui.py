"""Editor latency as a user sees it: from a change on the page to the first frame that shows it
(the preview) and to the refined frame, timed inside headless Chromium.

    .venv/bin/python benchmarks/bench_ui.py runs/demo [--repeats 10] [--size 256] [-o benchmarks/out/ui]

Opens `vq-mitsuba ui RUN_DIR` (in-process, free loopback port) in Chromium, clicks the object's
centre pixel to select its material, then for each repeat changes one control (roughness slider,
basecolor picker, preset, lighting rotation, an orbit drag). A MutationObserver on the view image
stamps each frame with `performance.now()`; the change is stamped just before its event is
dispatched (a drag: at its first mouse move). A drag sends several orbit requests: its refined
time is to the refined frame of the last one. Prints medians and writes OUT/ui_<commit>.json.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

OBSERVE = """
window.frames_seen = [];
const img = document.getElementById('frame');
new MutationObserver(() => window.frames_seen.push([performance.now(), +img.dataset.version, +img.dataset.spp]))
  .observe(img, {attributes: true, attributeFilter: ['data-spp']});
window.drag_t0 = null;  // the first mouse move of a drag: when the user starts turning the view
window.addEventListener('mousemove', (e) => { if (e.buttons && window.drag_t0 === null) window.drag_t0 = performance.now(); }, true);
"""

# One change per kind: JS run in the page at time t0 (returned), the change's events dispatched.
CHANGES = {
    "roughness slider": "const c = document.getElementById('roughness'); c.value = (0.2 + 0.6 * Math.random()).toFixed(2);"
                        "const t0 = performance.now(); c.dispatchEvent(new Event('input')); c.dispatchEvent(new Event('change')); return t0;",
    "basecolor picker": "const c = document.getElementById('basecolor'); c.value = '#' + Math.floor(Math.random() * 0xffffff).toString(16).padStart(6, '0');"
                        "const t0 = performance.now(); c.dispatchEvent(new Event('input')); c.dispatchEvent(new Event('change')); return t0;",
    "preset": "const c = document.getElementById('preset'); c.value = ['gold', 'copper', 'black_rubber', 'ceramic'][Math.floor(Math.random() * 4)];"
              "const t0 = performance.now(); c.dispatchEvent(new Event('change')); return t0;",
    "lighting rotation": "const c = document.getElementById('rotate'); c.value = Math.floor(-180 + 360 * Math.random());"
                         "const t0 = performance.now(); c.dispatchEvent(new Event('input')); return t0;",
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--size", type=int, default=256, help="the editor's view size (long side, px)")
    p.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "out" / "ui"))
    args = p.parse_args()

    from selenium.webdriver import ActionChains

    from provenance import provenance, write_result
    from vq_mitsuba.ui.browser import REFINED, click_pixel, headless_chromium, page_url, start_editor, \
        stop_editor, wait_page

    session, server = start_editor(args.run_dir, size=args.size)
    driver = headless_chromium()
    refine = session.state()["refine_spp"]

    def wait(script):
        return wait_page(driver, script, poll=0.02)

    refined_now = REFINED.format(spp=refine)
    results: dict[str, dict] = {}
    try:
        driver.get(page_url(server))
        wait(refined_now)
        img = driver.find_element("id", "frame")
        alpha = session.last_images["alpha"]
        ys, xs = (alpha > 0.5).nonzero()
        click_pixel(driver, session.camera, int(xs.mean()), int(ys.mean()))  # the object's centre pixel
        wait("return document.getElementById('frame').dataset.selected")
        wait(refined_now)
        driver.execute_script(OBSERVE)
        kinds = list(CHANGES) + ["orbit drag"]
        for kind in kinds:
            preview, refined, server_preview = [], [], []
            for _ in range(args.repeats):
                before = int(driver.execute_script("return +document.getElementById('frame').dataset.version"))
                driver.execute_script("window.frames_seen = []; window.drag_t0 = null;")
                if kind == "orbit drag":
                    ActionChains(driver).move_to_element(img).click_and_hold().move_by_offset(12, 0).release().perform()
                    t0 = driver.execute_script("return window.drag_t0")
                else:
                    t0 = driver.execute_script(CHANGES[kind])
                wait(f"return window.frames_seen.some(f => f[1] > {before} && f[2] >= {refine})")
                time.sleep(0.3)  # let a drag's last orbit request land before the next change
                wait(refined_now)
                seen = driver.execute_script("return window.frames_seen")
                new = [f for f in seen if f[1] > before]
                last = max(f[1] for f in new)  # a drag sends several orbits: time to the last one's frames
                first_new = min(f[0] for f in new)
                preview.append((first_new - t0) / 1000)
                refined.append((min(f[0] for f in new if f[1] == last and f[2] >= refine) - t0) / 1000)
                server_preview.append(session.frame.change_s)
            results[kind] = {"preview_s": preview, "refined_s": refined,
                             "preview_median_s": statistics.median(preview), "refined_median_s": statistics.median(refined)}
            print(f"{kind:18s} preview {statistics.median(preview):6.3f} s   refined ({refine} spp) "
                  f"{statistics.median(refined):6.2f} s   (median of {args.repeats})", flush=True)
    finally:
        driver.quit()
        stop_editor(session, server)

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    record = {"run": str(Path(args.run_dir).resolve()), "size": [session.camera.width, session.camera.height],
              "refine_spp": refine, "results": results}
    path = write_result(out / f"ui_{provenance()['commit']}.json", record)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
