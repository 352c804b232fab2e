"""`vq-mitsuba ui`: the editor's state, its server's rules, and the page in a real browser."""

import http.client
import io
import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from tiny_scene import THREE_MATERIALS, three_material_ids

SIZE = 96  # the editor's view size in these tests (long side, px)


@pytest.fixture(scope="module")
def editor(three_materials):
    """A running editor (session + server on a free loopback port) of the three-sphere run."""
    from vq_mitsuba.ui.browser import start_editor, stop_editor
    from vq_mitsuba.ui.session import PREVIEW, REFINE

    _, run = three_materials
    # refining stops at the refined frame: screenshots taken apart in time show equal samples
    session, server = start_editor(run.dir, size=SIZE, max_spp=PREVIEW[0] + 8 * REFINE[0])
    yield session, server
    stop_editor(session, server)


def _get(server, path, headers=None):
    conn = http.client.HTTPConnection(*server.server_address[:2], timeout=30)
    conn.request("GET", path, headers=headers or {})  # sent as written: no client-side normalisation of ../
    r = conn.getresponse()
    return r.status, r.read()


def _post(server, action, body, raw=None, headers=None):
    """POST as the page does (JSON, the session's token); `headers` replace or add (None: drop one)."""
    conn = http.client.HTTPConnection(*server.server_address[:2], timeout=60)
    data = raw if raw is not None else json.dumps(body).encode()
    sent = {"Content-Type": "application/json", "X-VQM-Token": server.token, **(headers or {})}
    conn.request("POST", f"/api/{action}", body=data, headers={k: v for k, v in sent.items() if v is not None})
    r = conn.getresponse()
    body = r.read()
    return r.status, json.loads(body) if r.getheader("Content-Type") == "application/json" else {"text": body}


def _sphere_pixel(session, k):
    """The pixel (x, y) of the current view at the centre of ground-truth sphere k."""
    centre = np.array(THREE_MATERIALS[k][0])
    toward_camera = session.camera.origin - centre
    surface = centre + 0.3 * toward_camera / np.linalg.norm(toward_camera)
    x, y = session.camera.project(surface[None])[0]
    return int(x), int(y)


def _wait_refined(session, version=None, timeout=120):
    from vq_mitsuba.ui.session import PREVIEW, REFINE

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        f = session.wait_frame(-1, -1, timeout=1)
        if f is not None and f.spp >= PREVIEW[0] + 8 * REFINE[0] and (version is None or f.version >= version):
            return f
        time.sleep(0.1)
    raise AssertionError("no refined frame")


def _wait_idle(session, timeout=180):
    """Until the render thread has refined the current state to the end and waits: the test may
    then render in its own thread (the editor renders on one thread only). Asks for frames, as an
    open page does, so that refining goes on."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        f = session.wait_frame(-1, -1, timeout=1)
        if f is not None and f.version == session.version and f.spp >= session.max_spp:
            return
        time.sleep(0.2)
    raise AssertionError("the editor never finished refining")


# --- the server: what it serves and what it refuses ---------------------------------------------------
def test_server_serves_the_page_and_the_runs_images_only(editor, tmp_path):
    import imageio.v3 as iio

    session, server = editor
    assert _get(server, "/")[0] == 200 and b"app.js" in _get(server, "/")[1]
    status, body = _get(server, "/run/materials_sheet.png")
    assert status == 200 and np.array_equal(iio.imread(io.BytesIO(body)),
                                            iio.imread(session.run.dir / "materials_sheet.png"))
    # what the page never shows is not served, though it lies in the run folder
    for name in ["checkpoint.pt", "config.yaml", "run.json", "materials.json", "mesh.ply", "fit.json"]:
        assert (session.run.dir / name).is_file(), name
        assert _get(server, f"/run/{name}")[0] == 404, name
    other = tmp_path / "other_run"
    other.mkdir()
    (other / "run.json").write_text("{}")
    for path in ["/run/../run.json", "/run/%2e%2e/run.json", "/run/..%2frun.json", "/run//etc/passwd",
                 "/run/%2Fetc%2Fpasswd", f"/run/{other / 'run.json'}", "/run/../other_run/run.json",
                 "/../../etc/passwd", "/static/../server.py", "/ui/server.py", "/run/", "/run/.",
                 "/run/C:%5Cwindows", "/etc/passwd"]:
        assert _get(server, path)[0] == 404, path
    # a link inside the run that leads out of it is refused too
    (session.run.dir / "link.json").symlink_to(other / "run.json")
    try:
        assert _get(server, "/run/link.json")[0] == 404
    finally:
        (session.run.dir / "link.json").unlink()


def test_server_binds_to_loopback_unless_a_host_is_given(editor):
    import inspect

    from vq_mitsuba.cli import build_parser
    from vq_mitsuba.ui.server import make_server, serve

    _, server = editor
    assert server.server_address[0] == "127.0.0.1"
    assert inspect.signature(make_server).parameters["host"].default == "127.0.0.1"
    assert inspect.signature(serve).parameters["host"].default == "127.0.0.1"
    assert build_parser().parse_args(["ui", "somerun"]).host == "127.0.0.1"


def test_bad_requests_are_refused_with_a_reason(editor):
    session, server = editor
    _wait_refined(session)
    status, body = _post(server, "select", None, raw=b"{not json")
    assert status == 400 and "JSON" in body["error"]
    status, body = _post(server, "select", {"pixel": [0, 0]})  # a corner: background
    assert status == 400 and "background" in body["error"]
    status, body = _post(server, "select", {"pixel": [SIZE + 5, 3]})
    assert status == 400 and "outside" in body["error"]
    status, body = _post(server, "select", {"materials": [99]})
    assert status == 400 and "materials 1.." in body["error"]
    assert _post(server, "select", {"materials": []})[0] == 200
    status, body = _post(server, "edit", {"changes": [{"key": "roughness", "value": 0.5}]})
    assert status == 400 and "select" in body["error"]
    assert _post(server, "select", {"materials": [1]})[0] == 200
    status, body = _post(server, "edit", {"changes": [{"key": "roughness", "value": 7}]})
    assert status == 400 and "roughness" in body["error"]
    status, body = _post(server, "edit", {"changes": [{"key": "basecolor", "value": "#12345"}]})
    assert status == 400 and "#RRGGBB" in body["error"]
    for name in ["../escape", "/tmp/x", "", ".."]:
        status, body = _post(server, "save", {"name": name})
        assert status == 400, name
    status, body = _post(server, "select", {"materials": [1]}, headers={"Content-Type": "text/plain"})
    assert status == 415 and "application/json" in body["error"]
    status, body = _post(server, "lighting", {"envmap": "../../secret.exr"})
    assert status == 400 and "no envmap" in body["error"]
    assert _post(server, "no-such-action", {})[0] == 404
    assert session.edits() == []  # nothing was recorded by the refused requests


def test_relighting_from_the_envmap_folder(editor, tmp_path):
    from vq_mitsuba.data.imageio import write_exr

    session, server = editor
    folder = tmp_path / "envmaps"
    folder.mkdir()
    write_exr(folder / "bright.exr", np.full((16, 32, 3), 4.0, np.float32))
    (folder / "notes.txt").write_text("not an envmap")
    session.envmap_dir = folder
    assert _get(server, "/api/state")[0] == 200 and session.state()["envmaps"] == ["fitted", "bright.exr"]
    base = _wait_refined(session).version
    fitted = session.last_images["rgb"].mean()
    status, _ = _post(server, "lighting", {"envmap": "bright.exr", "rotate": 30, "exposure": 1})
    assert status == 200
    _wait_refined(session, base + 1)
    assert session.last_images["rgb"].mean() > 2 * fitted
    assert _post(server, "lighting", {"envmap": "fitted", "rotate": 0, "exposure": 100})[0] == 400
    assert _post(server, "lighting", {"envmap": "fitted"})[0] == 200


def test_every_display_mode_draws_its_map(editor):
    import imageio.v3 as iio

    session, server = editor
    _wait_refined(session)
    pictures = {}
    for mode in session.state()["modes"]:
        assert _post(server, "mode", {"mode": mode})[0] == 200
        status, png = _get(server, "/api/frame?version=-1&spp=-1")
        assert status == 200
        pictures[mode] = iio.imread(io.BytesIO(png))
    assert set(pictures) == {"render", "segmentation", "basecolor", "metallic", "roughness", "normal"}
    hits = session.last_images["alpha"] > 0.5
    for a in pictures:
        for b in pictures:
            if a < b:
                assert np.abs(pictures[a][hits].astype(int) - pictures[b][hits]).mean() > 2, (a, b)
    assert _post(server, "mode", {"mode": "depth"})[0] == 400
    assert _post(server, "mode", {"mode": "render"})[0] == 200


def test_the_command_prints_its_address_and_stops_on_ctrl_c(three_materials):
    import os
    import signal
    import subprocess
    import sys

    _, run = three_materials
    proc = subprocess.Popen([sys.executable, "-m", "vq_mitsuba.cli", "ui", str(run.dir), "--port", "0", "--size", "32"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = [proc.stdout.readline()]
        while "http://" not in lines[-1] and lines[-1] and len(lines) < 50:  # warnings may come first
            lines.append(proc.stdout.readline())
        line = lines[-1]
        assert "http://127.0.0.1:" in line, lines
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        conn.request("GET", "/")
        assert conn.getresponse().status == 200
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=60) == 0
        assert "stopping" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)


def test_other_web_pages_and_foreign_hosts_are_refused(editor):
    """A page on another origin cannot drive the editor (even with a body the browser sends without
    asking: text/plain), nor reach it under another host name (DNS rebinding)."""
    session, server = editor
    port = server.server_address[1]
    session.select(materials=[1])
    session.edit([{"key": "roughness", "value": 0.7}])
    before = (session.position, len(session.history), session.selection)
    folders = sorted(p.name for p in session.run.dir.parent.iterdir())
    evil = {"Origin": "http://evil.example"}
    for action, body in [("undo", {}), ("save", {"name": "from-evil"}), ("select", {"materials": [2]})]:
        status, answer = _post(server, action, body, headers={**evil, "Content-Type": "text/plain"})
        assert status == 403, (action, answer)
        status, answer = _post(server, action, body, headers=evil)  # even with the token (it cannot have it)
        assert status == 403 and "other web pages" in answer["error"], (action, answer)
        status, answer = _post(server, action, body, headers={"X-VQM-Token": None})  # our origin, no token
        assert status == 403 and "X-VQM-Token" in answer["error"], (action, answer)
        status, answer = _post(server, action, body, headers={"X-VQM-Token": server.token[:-1] + "x"})
        assert status == 403, (action, answer)
        for origin in ("null", f"http://evil.example:{port}", f"https://127.0.0.1:{port}", "http://127.0.0.1:1"):
            assert _post(server, action, body, headers={"Origin": origin})[0] == 403, (action, origin)
    for host in ("evil.example", f"evil.example:{port}", "127.0.0.1:1", f"127.0.0.1.evil.example:{port}"):
        for path in ("/", "/api/state", "/run/materials_sheet.png", "/app.js"):
            status, body = _get(server, path, headers={"Host": host})
            assert status == 403 and server.token.encode() not in body, (host, path)
        assert _post(server, "undo", {}, headers={"Host": host})[0] == 403, host
    assert (session.position, len(session.history), session.selection) == before
    assert sorted(p.name for p in session.run.dir.parent.iterdir()) == folders
    # the editor's own addresses are served, and the page holds the token
    for host in (f"127.0.0.1:{port}", f"localhost:{port}"):
        status, body = _get(server, "/", headers={"Host": host})
        assert status == 200 and server.token.encode() in body
        assert _get(server, "/api/state", headers={"Host": host, "Origin": f"http://{host}"})[0] == 200
    status, _ = _post(server, "undo", {}, headers={"Origin": f"http://localhost:{port}", "Host": f"localhost:{port}"})
    assert status == 200 and session.position == before[0] - 1
    session.select(materials=[])


def test_each_server_has_its_own_token(editor):
    from vq_mitsuba.ui.server import make_server

    session, server = editor
    other = make_server(session, port=0)
    try:
        assert other.token != server.token and len(server.token) >= 32
    finally:
        other.server_close()


def test_the_addresses_a_server_answers_to():
    from vq_mitsuba.ui.server import allowed_hosts

    assert allowed_hosts("127.0.0.1", 8080) == {"127.0.0.1:8080", "localhost:8080", "[::1]:8080"}
    assert "localhost" in allowed_hosts("127.0.0.1", 80)  # a browser leaves out the default port
    assert allowed_hosts("192.168.1.7", 8080) == {"192.168.1.7:8080"}  # not every name of the machine
    wildcard = allowed_hosts("0.0.0.0", 8080)
    assert "localhost:8080" in wildcard and not any(h.startswith("0.0.0.0") for h in wildcard)


def test_refining_pauses_when_no_page_asks_for_frames(editor):
    session, _ = editor
    idle_s, max_spp = session.idle_s, session.max_spp
    session.idle_s, session.max_spp = 0.5, 1 << 20  # refining would go on for minutes
    try:
        session.set_view(session.view_name)  # a change: previewed, then refined while asked
        first = _wait_refined(session, session.version)
        deadline = time.monotonic() + 60
        spp = [session.frame.spp]
        while time.monotonic() < deadline:  # nobody asks now: the samples stop growing
            time.sleep(2.0)
            spp.append(session.frame.spp)
            if spp[-1] == spp[-2]:
                break
        assert spp[-1] == spp[-2] and spp[-1] < session.max_spp, spp
        time.sleep(1.0)
        assert session.frame.spp == spp[-1]
        # a page asks again: refining goes on from where it stopped
        newer = session.wait_frame(session.frame.version, spp[-1], timeout=30)
        assert newer.version == first.version and newer.spp > spp[-1]
    finally:
        session.idle_s, session.max_spp = idle_s, max_spp
        _wait_idle(session)


# --- the session: edits, undo / redo, orbit --------------------------------------------------------
def test_live_slider_changes_merge_and_undo_redo_walk_the_history(editor):
    session, _ = editor
    session.select(materials=[1])
    for v in (0.2, 0.3, 0.4):
        session.edit([{"key": "roughness", "value": v}], live=True)
    session.edit([{"key": "roughness", "value": 0.45}], live=False)  # the slider is released
    assert [e.changes[0].value for e in session.edits()] == [0.45]
    session.edit([{"key": "roughness", "value": 0.6}], live=True)  # a new drag: a new entry
    session.edit([{"key": "basecolor", "value": "#ff0000"}])
    assert len(session.edits()) == 3 and session.edits()[2].changes[0].value == pytest.approx((1.0, 0.0, 0.0))
    assert session.edits()[0].label == "--material 1 --set roughness=0.45"
    session.undo()
    session.undo()
    assert [e.changes[0].value for e in session.edits()] == [0.45]
    session.redo()
    assert len(session.edits()) == 2
    session.edit(preset="gold")  # a new edit after an undo drops what could be redone
    assert len(session.edits()) == 3 and session.edits()[-1].label == "--material 1 --preset gold"
    with pytest.raises(Exception, match="nothing to redo"):
        session.redo()
    while session.state()["can_undo"]:
        session.undo()
    assert session.edits() == []


def test_the_panel_values_follow_presets_undo_and_redo(editor):
    """state()["materials"] holds each material's values as the edits leave them (what the page's
    material panel shows)."""
    from vq_mitsuba.models.material_edits import material_library

    session, _ = editor
    values = lambda: {m["id"]: m for m in session.state()["materials"]}  # noqa: E731
    fitted = values()
    gold = material_library()["gold"]
    session.select(materials=[2])
    session.edit(preset="gold")
    now = values()
    assert now[2]["basecolor"] == pytest.approx(gold["basecolor"]) and now[2]["metallic"] == gold["metallic"]
    assert now[2]["roughness"] == pytest.approx(gold["roughness"])
    assert now[1] == fitted[1] and now[3] == fitted[3]
    session.edit([{"op": "scale", "key": "roughness", "value": 0.5}])
    assert values()[2]["roughness"] == pytest.approx(gold["roughness"] * 0.5)
    session.undo()
    assert values()[2]["roughness"] == pytest.approx(gold["roughness"])
    session.undo()
    assert values() == fitted
    session.redo()
    assert values()[2]["metallic"] == gold["metallic"]
    # an edit inside a box changes part of the material: it shows while that box is selected
    lo, hi = session.bounds[0].tolist(), session.bounds.mean(0).tolist()
    session.select(materials=[2], box=[lo, hi])
    session.edit([{"key": "metallic", "value": 0.0}])
    assert values()[2]["metallic"] == 0.0
    session.select(materials=[2])
    assert values()[2]["metallic"] == gold["metallic"]
    while session.state()["can_undo"]:
        session.undo()
    session.select(materials=[])


def test_orbit_turns_about_the_object_and_stops_short_of_the_poles():
    from vq_mitsuba.data.cameras import look_at
    from vq_mitsuba.ui.session import orbit

    centre, up = np.array([0.1, 0.2, 0.3]), np.array([0.0, 1.0, 0.0])
    cam = look_at([2.0, 1.0, 2.5], centre, up)
    turned = orbit(cam, centre, up, 37.0, 12.0)
    assert np.linalg.norm(turned[:3, 3] - centre) == pytest.approx(np.linalg.norm(cam[:3, 3] - centre))
    forward = turned[:3, 2]
    assert forward @ (centre - turned[:3, 3]) / np.linalg.norm(centre - turned[:3, 3]) == pytest.approx(1.0)
    assert np.allclose(orbit(orbit(cam, centre, up, 50.0, 0.0), centre, up, -50.0, 0.0), cam)
    elevation = lambda m: np.degrees(np.arcsin(-m[:3, 2] @ up))  # noqa: E731  (> 0: looking down)
    assert elevation(orbit(cam, centre, up, 0.0, 10.0)) == pytest.approx(elevation(cam) + 10.0)
    for pitch, stop in ((400.0, 85.0), (-400.0, -85.0)):  # dragging far past a pole stops 5 degrees short
        assert elevation(orbit(cam, centre, up, 0.0, pitch)) == pytest.approx(stop)
    closer = orbit(cam, centre, up, 0.0, 0.0, zoom=0.5)
    assert np.linalg.norm(closer[:3, 3] - centre) == pytest.approx(0.5 * np.linalg.norm(cam[:3, 3] - centre))


def test_a_saved_edit_renders_as_the_editor_showed_it_and_exports(editor, three_materials, tmp_path):
    from vq_mitsuba.cli import main
    from vq_mitsuba.data.imageio import read_exr
    from vq_mitsuba.run.run_dir import RunDir
    from vq_mitsuba.render.views import render_views

    capture, run = three_materials
    session, server = editor
    session.select(materials=[2])
    session.edit([{"key": "basecolor", "value": "#20c040"}, {"key": "roughness", "value": 0.2}])
    name = f"saved-{tmp_path.name}"
    status, body = _post(server, "save", {"name": name})
    assert status == 200
    saved = RunDir(body["path"])
    assert saved.dir.parent == run.dir.resolve().parent and saved.is_edit()
    assert [e.to_dict() for e in saved.edits()] == [e.to_dict() for e in session.edits()]
    _wait_idle(session)
    # `vq-mitsuba render` of the saved run against the editor's own fitted model with its edits
    assert main(["render", str(saved.dir), "--cameras", str(capture), "-o", str(tmp_path / "cli"), "--spp", "16",
                 "--quiet"]) == 0
    fitted = run.load()
    fitted.edits = session.edits()
    cams = run.cameras()["train"][:2]
    render_views(fitted, cams, fitted.world, tmp_path / "ours", spp=16)
    for cam in cams:
        a, b = read_exr(tmp_path / "cli" / f"{cam.name}_rgb.exr"), read_exr(tmp_path / "ours" / f"{cam.name}_rgb.exr")
        assert np.array_equal(a, b)
    # a second save under the name of a fitted run is refused, and so is one over an edit list that
    # `vq-mitsuba edit` wrote (this editor saved only `name`)
    assert _post(server, "save", {"name": run.dir.name})[0] == 400
    other = run.dir.resolve().parent / f"other-{tmp_path.name}"
    assert main(["edit", str(run.dir), "--material", "1", "--set", "roughness=0.9", "-o", str(other)]) == 0
    before = (other / RunDir.EDITS).read_bytes()
    status, body = _post(server, "save", {"name": other.name})
    assert status == 400 and "did not save" in body["error"]
    assert (other / RunDir.EDITS).read_bytes() == before
    shutil.rmtree(other)
    # export from the page: saved again, then baked and written on the render thread
    status, body = _post(server, "export", {"name": name, "format": "gltf", "texture_size": 64})
    assert status == 200
    deadline = time.monotonic() + 180
    while session.state()["job"]["state"] == "running" and time.monotonic() < deadline:
        time.sleep(0.5)
    job = session.state()["job"]
    assert job["state"] == "done", job
    assert list(Path(job["path"]).glob("*.glb"))
    session.undo()
    shutil.rmtree(saved.dir)


# --- the page in a real browser ----------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    """Headless Chromium driven by Selenium (Debian's chromium and chromium-driver, `make chromium`)."""
    pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[dev]')")
    from vq_mitsuba.ui.browser import headless_chromium

    try:
        driver = headless_chromium()
    except RuntimeError as exc:  # not installed
        pytest.skip(str(exc))
    except Exception as exc:  # e.g. no display libraries in a container
        pytest.skip(f"Chromium cannot run here: {exc}")
    yield driver
    driver.quit()


def _frame_image(driver) -> np.ndarray:
    """The view as the browser shows it (a screenshot of the image element), at the frame's own size."""
    import imageio.v3 as iio

    img = driver.find_element("id", "frame")
    shot = iio.imread(io.BytesIO(img.screenshot_as_png))[..., :3].astype(np.float64)
    w = int(driver.execute_script("return arguments[0].naturalWidth", img))
    scale = shot.shape[1] // w
    return shot[scale // 2::scale, scale // 2::scale][: shot.shape[0] // scale, :w]


def test_browser_click_selects_a_material_and_recolours_only_it(editor, browser):
    from vq_mitsuba.data.cameras import camera_rays
    from vq_mitsuba.edit import material_under_pixel
    from vq_mitsuba.render.shading import scene_for_mesh
    from vq_mitsuba.ui.browser import click_pixel, page_url, wait_page

    session, server = editor
    # direct light only: a pixel outside material K can then change only if the edit leaked there
    # (with interreflections, what mirrors K changes too)
    bounces = session.fitted.cfg.train.bounces
    session.fitted.cfg.train.bounces = 0
    _wait_idle(session)  # the render thread waits while its renderers are dropped
    session._renderers.clear()
    session.select(materials=[])
    session.set_view(session.view_name)  # render again from scratch
    refined = session.state()["refine_spp"]
    browser.get(page_url(server))
    wait_refined = ("const i = document.getElementById('frame'); "
                    f"return +i.dataset.spp >= {refined} && +i.dataset.version >= arguments[0] && i.complete;")
    wait_page(browser, wait_refined.replace("arguments[0]", "0"))

    sphere = 0  # the rough red sphere
    x, y = _sphere_pixel(session, sphere)
    click_pixel(browser, session.camera, x, y)
    k = int(wait_page(browser, "return document.getElementById('frame').dataset.selected"))
    # the page picked what `vq-mitsuba edit --pick` picks, and that material is the red sphere's
    assert k == material_under_pixel(session.fitted, session.camera, x, y)
    version = session.frame.version
    wait_page(browser, wait_refined.replace("arguments[0]", str(version)))
    region = session.last_images["material"] == k
    hits = session.last_images["alpha"] > 0.5
    before = _frame_image(browser)
    shown = int(browser.execute_script("return document.getElementById('frame').dataset.version"))

    browser.execute_script("const c = document.getElementById('basecolor'); c.value = '#2040ff'; "
                           "c.dispatchEvent(new Event('input')); c.dispatchEvent(new Event('change'));")
    wait_page(browser, "return document.querySelectorAll('#edits li').length === 1")
    assert browser.find_element("id", "edits").text.startswith(f"--material {k} --set basecolor=")
    wait_page(browser, wait_refined.replace("arguments[0]", str(shown + 1)))
    after = _frame_image(browser)

    changed = np.abs(after - before).max(-1) > 12
    grown = region.copy()  # the region grown by one pixel (edges mix two materials)
    grown[1:] |= region[:-1]; grown[:-1] |= region[1:]; grown[:, 1:] |= region[:, :-1]; grown[:, :-1] |= region[:, 1:]
    inner = region.copy()  # the region less its outline (drawn alike before and after)
    inner[1:] &= region[:-1]; inner[:-1] &= region[1:]; inner[:, 1:] &= region[:, :-1]; inner[:, :-1] &= region[:, 1:]
    assert inner.sum() > 30
    assert changed[inner].mean() > 0.95, "the selected material did not change"
    # outside it nothing changed: the same samples, and no light from K reaches other pixels directly
    assert not changed[hits & ~grown].any()
    chroma = lambda rgb: rgb / np.maximum(rgb.sum(-1, keepdims=True), 1)  # noqa: E731
    target = chroma(np.array([0x20, 0x40, 0xff], float))
    assert np.linalg.norm(chroma(after[region]).mean(0) - target) < 0.5 * np.linalg.norm(chroma(before[region]).mean(0) - target)
    # and the clicked point is on the red sphere in the ground truth
    o, d = camera_rays(session.camera, pixels=np.array([y * session.camera.width + x]))
    hit = scene_for_mesh(session.fitted.mesh, session.fitted.envmap, session.fitted.envmap_to_world).trace(o, d)
    assert three_material_ids(hit.position.cpu().numpy())[0] == sphere + 1
    session.undo()
    session.fitted.cfg.train.bounces = bounces
    _wait_idle(session)
    session._renderers.clear()


def test_browser_panel_shows_the_values_after_a_preset_undo_and_redo(editor, browser):
    """The page (its POSTs carry the token it was served) applies a preset to the selected material;
    the sliders and the colour then show the preset's values, and the fitted ones again after undo."""
    from vq_mitsuba.data.imageio import linear_to_srgb
    from vq_mitsuba.models.material_edits import material_library
    from vq_mitsuba.ui.browser import page_url, wait_page

    session, server = editor
    session.select(materials=[])
    while session.state()["can_undo"]:
        session.undo()
    browser.get(page_url(server))
    wait_page(browser, "return document.querySelectorAll('#materials li').length === 3")
    fitted = {m["id"]: m for m in session.state()["materials"]}

    def panel_shows(m):
        srgb8 = (np.clip(linear_to_srgb(np.asarray(m["basecolor"], np.float64)), 0, 1) * 255).tolist()
        wait_page(browser, "const v = (id) => document.getElementById(id).value; "
                           "const c = [1, 3, 5].map((i) => parseInt(v('basecolor').slice(i, i + 2), 16)); "
                           f"return c.every((x, i) => Math.abs(x - {srgb8}[i]) <= 1) && "
                           f"Math.abs(v('metallic') - {m['metallic']}) < 0.006 && "
                           f"Math.abs(v('roughness') - {m['roughness']}) < 0.006", timeout=60)

    browser.find_element("css selector", "#materials li[data-id='2']").click()
    wait_page(browser, "return document.getElementById('frame').dataset.selected === '2'")
    panel_shows(fitted[2])
    gold = material_library()["gold"]
    assert abs(fitted[2]["roughness"] - gold["roughness"]) > 0.05  # the preset moves the sliders
    browser.execute_script("const p = document.getElementById('preset'); p.value = 'gold'; "
                           "p.dispatchEvent(new Event('change'));")
    wait_page(browser, "return document.querySelectorAll('#edits li').length === 1")
    assert browser.find_element("id", "edits").text == "--material 2 --preset gold"
    assert [e.label for e in session.edits()] == ["--material 2 --preset gold"]  # the token was accepted
    panel_shows(gold)
    browser.find_element("id", "undo").click()
    wait_page(browser, "return document.querySelectorAll('#edits li').length === 0")
    panel_shows(fitted[2])
    browser.find_element("id", "redo").click()
    panel_shows(gold)
    # a slider touched now starts from the preset's values: only roughness changes
    browser.execute_script("const r = document.getElementById('roughness'); r.value = '0.6'; "
                           "r.dispatchEvent(new Event('change'));")
    wait_page(browser, "return document.querySelectorAll('#edits li').length === 2")
    assert session.state()["materials"][1]["metallic"] == gold["metallic"]
    assert session.state()["materials"][1]["roughness"] == pytest.approx(0.6)
    while session.state()["can_undo"]:
        session.undo()
    session.select(materials=[])
