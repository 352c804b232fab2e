"""The editor against a hostile page: concurrent saves of one name each get a right answer and leave
one whole edited run, names and values it cannot use are refused with a sentence (never Python's
own text), an export it would refuse saves nothing, and its host messages say what is wrong."""

import threading

import pytest

from test_ui import _post
from vq_mitsuba.errors import InputError
from vq_mitsuba.run.run_dir import RunDir, write_atomic


@pytest.fixture(scope="module")
def editor(three_materials):
    from vq_mitsuba.ui.browser import start_editor, stop_editor

    _, run = three_materials
    session, server = start_editor(run.dir, size=32, max_spp=8)
    yield session, server, run
    stop_editor(session, server)


def test_concurrent_saves_of_one_name_all_answer_and_leave_one_whole_run(editor):
    session, server, run = editor
    assert _post(server, "select", {"materials": [1]})[0] == 200
    assert _post(server, "edit", {"changes": [{"key": "roughness", "value": 0.4}]})[0] == 200
    answers = []

    def save():
        answers.append(_post(server, "save", {"name": "twice_saved"}))

    threads = [threading.Thread(target=save) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert len(answers) == 8 and all(status == 200 for status, _ in answers), answers
    saved = RunDir(run.dir.parent / "twice_saved")
    assert saved.is_edit() and len(saved.edits()) == 1
    assert not [p for p in saved.dir.iterdir() if ".tmp" in p.name]  # no writer's leftovers


def test_a_name_that_is_a_file_is_refused_with_a_message(editor):
    _, server, run = editor
    (run.dir.parent / "a_file").write_text("mine")
    status, answer = _post(server, "save", {"name": "a_file"})
    assert status == 400 and "is a file, not a folder" in answer["error"]
    assert (run.dir.parent / "a_file").read_text() == "mine"


@pytest.mark.parametrize("change, words", [
    ({"op": "scale", "key": "roughness", "value": 1e308}, "factor must lie in [0, 1000]"),
    ({"op": "hue_shift", "key": "basecolor", "value": 1e308}, "degrees must lie in"),
    ({"key": "metallic", "value": "x"}, "the value of 'metallic' must be a number"),
    ({"value": 0.3}, "a change without 'key'"),
])
def test_edit_values_out_of_range_are_refused(editor, change, words):
    _, server, _ = editor
    assert _post(server, "select", {"materials": [1]})[0] == 200
    status, answer = _post(server, "edit", {"changes": [change]})
    assert status == 400 and words in answer["error"] and "float()" not in answer["error"]


@pytest.mark.parametrize("body, words", [
    ({"yaw": "left"}, "'yaw' must be a finite number, got 'left'"),
    ({"yaw": 1, "zoom": None}, "'zoom' must be a finite number, got None"),
])
def test_request_values_are_named_not_shown_as_python_text(editor, body, words):
    _, server, _ = editor
    status, answer = _post(server, "orbit", body)
    assert status == 400 and answer["error"].endswith(words) and "float()" not in answer["error"]


def test_a_request_without_a_field_names_it(editor):
    _, server, _ = editor
    status, answer = _post(server, "view", {})
    assert status == 400 and answer["error"] == "the request has no 'name'"


@pytest.mark.parametrize("size", [1e8, -4, 1.5, "big"])
def test_an_export_it_would_refuse_saves_nothing(editor, size):
    _, server, run = editor
    name = "never_saved"
    status, answer = _post(server, "export", {"name": name, "format": "obj", "texture_size": size})
    assert status == 400 and answer["error"].startswith("'texture_size' must be a whole number"), answer
    assert not (run.dir.parent / name).exists()


# Python's own words for a wrong type or value, which the editor never answers with
PYTHON_TEXT = ("invalid literal", "indices must", "object is not", "object has no", "NoneType", "float()", "int()",
               "not iterable", "not subscriptable", "unhashable", "convert", "positional argument", "cannot do that")


@pytest.mark.parametrize("action, body, words", [
    ("select", {"materials": "all"}, "'materials' must be a list of material numbers (whole numbers; this run's: 1..3)"),
    ("select", {"materials": [1.5]}, "'materials' must be a list of material numbers"),
    ("select", {"materials": [True]}, "'materials' must be a list of material numbers"),
    ("select", {"materials": {"1": 1}}, "'materials' must be a list of material numbers"),
    ("select", {"pixel": "3,4"}, "'pixel' must be two whole numbers [x, y]"),
    ("select", {"pixel": [1]}, "'pixel' must be two whole numbers [x, y]"),
    ("select", {"box": [[0, 0, 0], [1, 1, None]]}, "'box' must be two corners of three finite numbers"),
    ("select", {"box": "x"}, "'box' must be two corners of three finite numbers"),
    ("select", {"add": "yes"}, "'add' must be true or false, got 'yes'"),
    ("select", {"material": [1]}, "unknown field 'material' (/api/select takes materials, box, pixel, add)"),
    ("edit", {"changes": "x"}, "'changes' must be a list of changes"),
    ("edit", {"changes": ["x"]}, "'changes[0]' must be a change"),
    ("edit", {"changes": [{"key": 5, "value": 1}]}, "'changes[0].key' must be one of basecolor, metallic, roughness"),
    ("edit", {"changes": [{"key": "roughness", "value": 0.5, "op": 3}]}, "'changes[0].op' must be one of set, scale"),
    ("edit", {"changes": [{"key": "roughness", "value": 0.5, "by": 1}]}, "'changes[0]' has an unknown field 'by'"),
    ("edit", {"changes": [{"key": "roughness", "value": 10 ** 400}]}, "the value of 'roughness' must be a number"),
    ("edit", {"changes": [{"key": "roughness", "value": True}]}, "the value of 'roughness' must be a number"),
    ("edit", {"preset": 5}, "'preset' must be the name of a library material"),
    ("edit", {"live": "no"}, "'live' must be true or false"),
    ("view", {"name": 5}, "'name' must be a string, got 5"),
    ("mode", {"mode": ["render"]}, "'mode' must be a string"),
    ("orbit", {"yaw": 10 ** 400}, "'yaw' must be a finite number"),
    ("orbit", {"pitch": True}, "'pitch' must be a finite number, got True"),
    ("orbit", {"zoom": 9}, "'zoom' must be a number from 0.2 to 5, got 9"),
    ("lighting", {"envmap": 3}, "'envmap' must be a string, got 3"),
    ("lighting", {"rotate": "x"}, "'rotate' must be a finite number"),
    ("lighting", {"exposure": 100}, "'exposure' must be a number from -64 to 64, got 100"),
    ("save", {"name": ["a"]}, "'name' must be a string"),
    ("save", {}, "the request has no 'name'"),
    ("export", {"name": "never_exported", "format": 3}, "'format' must be a string, got 3"),
    ("undo", {"steps": 2}, "unknown field 'steps' (/api/undo takes no fields)"),
])
def test_every_wrong_field_is_named_with_what_it_must_be(editor, action, body, words):
    session, server, run = editor
    before = (session.position, len(session.history), session.selection, session.view_name, session.mode)
    status, answer = _post(server, action, body)
    assert status == 400 and words in answer["error"], answer
    assert not any(text in answer["error"] for text in PYTHON_TEXT), answer
    assert (session.position, len(session.history), session.selection, session.view_name, session.mode) == before
    assert not (run.dir.parent / "never_exported").exists()


def test_a_frame_query_names_its_wrong_parameter(editor):
    from test_ui import _get

    _, server, _ = editor
    status, answer = _get(server, "/api/frame?version=1&spp=many")
    assert status == 400 and b"'spp' must be a whole number, got 'many'" in answer


def test_concurrent_atomic_writes_of_one_file_never_collide(tmp_path):
    """Every writer has its own temporary file: eight writers of one path all finish, and the file
    is one of theirs, whole."""
    path = tmp_path / "f.txt"
    errors = []

    def write(i):
        try:
            for _ in range(20):
                write_atomic(path, lambda tmp: tmp.write_text(str(i) * 1000))
        except Exception as exc:  # noqa: BLE001 - any failure is the finding
            errors.append(exc)

    threads = [threading.Thread(target=write, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(set(path.read_text())) == 1 and len(path.read_text()) == 1000
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]


@pytest.mark.parametrize("host, words", [
    ("no-such-host.invalid", "--host no-such-host.invalid: no such host name"),
    ("10.255.255.1", "--host 10.255.255.1: not an address of this machine"),
])
def test_a_bad_host_is_named(editor, host, words):
    from vq_mitsuba.ui.server import make_server

    session, _, _ = editor
    with pytest.raises(InputError, match=words):
        make_server(session, host, 0)


def test_any_loopback_address_is_loopback():
    from vq_mitsuba.ui.server import _loopback

    assert _loopback("127.0.0.2") and _loopback("::1") and _loopback("localhost")
    assert not _loopback("0.0.0.0") and not _loopback("192.168.1.4")


def test_a_truncated_materials_json_is_read_alike_by_the_editor_render_and_export(three_materials, tmp_path):
    """materials.json is a product for people: render and export never needed it, and the editor
    opens without it too (a warning, a material list without values) instead of refusing the run."""
    import shutil

    from vq_mitsuba.ui.session import EditorSession

    capture, run = three_materials
    copy = tmp_path / "run"
    shutil.copytree(run.dir, copy)
    text = (copy / RunDir.MATERIALS).read_text()
    (copy / RunDir.MATERIALS).write_text(text[: len(text) // 2])
    with pytest.warns(UserWarning, match="materials.json"):
        session = EditorSession(copy, size=16)
        listed = session._materials()
    assert listed and all(m["roughness"] is None for m in listed)
    from vq_mitsuba import cli

    assert cli.main(["render", str(copy), "--cameras", str(capture), "-o", str(tmp_path / "views"), "--spp", "1",
                     "--quiet"]) == 0
