"""Fuzz of the editor's JSON API (Hypothesis): sequences of requests to every action with fields
of any JSON type and value (huge, negative, of the wrong type, unknown), and raw bodies that are
no JSON object (deeply nested, NaN, not UTF-8, too large). Each request is answered: 200, or a 4xx
whose error is a sentence in the tool's words (never Python's text, never a dropped connection);
a field of the wrong type is named; Save writes only a folder of its name beside the run.

The session is not started: no frame is drawn and an export is queued, not run, so an example
costs a request, not a render."""

import json
import shutil
import threading

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fuzzing import files_under, fuzz, python_text
from test_ui import _post

FUZZ = fuzz(120)


@pytest.fixture(scope="module")
def api(three_materials, tmp_path_factory):
    """(server, the folder its run's copy lies in, the names sent to Save or Export so far) for an
    editor session that draws nothing."""
    from vq_mitsuba.ui.server import make_server
    from vq_mitsuba.ui.session import EditorSession

    _, run = three_materials
    folder = tmp_path_factory.mktemp("editor_fuzz")
    shutil.copytree(run.dir, folder / "run")
    server = make_server(EditorSession(folder / "run", size=16), "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("vq_mitsuba.ui.session.FRAME_TIMEOUT_S", 0.0)  # a pixel's pick waits for no frame
        yield server, folder, set()
    server.shutdown()
    server.server_close()


json_scalars = (st.none() | st.booleans() | st.integers(-3, 5) | st.sampled_from([10 ** 30, -(10 ** 30), 2 ** 63])
                | st.floats(allow_nan=False, allow_infinity=False) | st.sampled_from([1e308, -1e-308, 0.5, 4.0])
                | st.text(max_size=6) | st.sampled_from(["", "all", "x", "..", "../x", "a/b", "fitted", "render",
                                                        "roughness", "basecolor", "#ff0000", "gltf", "obj", "1024"]))
json_values = st.recursive(json_scalars, lambda inner: st.lists(inner, max_size=4)
                           | st.dictionaries(st.sampled_from(["key", "value", "op", "x"]) | st.text(max_size=3),
                                             inner, max_size=3), max_leaves=8)
changes = st.lists(st.fixed_dictionaries({"key": st.sampled_from(["basecolor", "metallic", "roughness"]) | json_values,
                                          "value": json_values | st.sampled_from([0.3, [0.1, 0.2, 0.3], 2.0, -1.0])},
                                         optional={"op": st.sampled_from(["set", "scale", "hue_shift"]) | json_values}),
                   min_size=1, max_size=3)
# values an action can do something with, drawn as often as any value
usable = {"materials": st.just([1]) | st.lists(st.integers(-1, 4), max_size=3), "changes": changes,
          "box": st.just([[-1, -1, -1], [1, 1, 1]]), "pixel": st.just([8, 8]),
          "name": st.sampled_from(["saved", "saved_2", "run", "view_0"]), "mode": st.sampled_from(["render", "material"]),
          "format": st.sampled_from(["obj", "gltf", "mitsuba"]), "texture_size": st.sampled_from([16, 64, 0, 9000]),
          "yaw": st.sampled_from([10, -400]), "zoom": st.sampled_from([1, 0.1, 6]), "preset": st.sampled_from(["gold"])}


@st.composite
def requests(draw):
    """1 to 4 (action, body): mostly the action's own fields, now and then another one."""
    from vq_mitsuba.ui.server import ACTIONS

    steps = []
    for _ in range(draw(st.integers(1, 4))):
        action = draw(st.sampled_from(sorted(ACTIONS) + ["nothere"]))
        taken = list(ACTIONS.get(action, ((),))[0])
        every = sorted({f for fields, _ in ACTIONS.values() for f in fields})
        keys = draw(st.lists(st.sampled_from(taken) if taken and draw(st.integers(0, 4)) else st.sampled_from(every),
                             min_size=1 if taken else 0, max_size=3, unique=True))
        steps.append((action, {k: draw(usable[k] | json_values if k in usable else json_values) for k in keys}))
    return steps


def _answered(server, action, body=None, raw=None) -> tuple[int, str]:
    """(status, error) of a request; the error is a sentence in the tool's words."""
    status, answer = _post(server, action, body, raw=raw)
    assert status == 200 or 400 <= status < 500, (status, answer)
    error = answer.get("error", "") if status != 200 else ""
    if status == 200:
        assert answer.get("ok") is True and "state" in answer
    elif status != 404:
        assert error and not python_text(error) and not error.startswith("cannot do that"), error
    return status, error


@FUZZ
@given(steps=requests())
def test_any_request_is_answered_in_words(api, steps):
    server, folder, names = api
    for action, body in steps:
        if isinstance(body.get("name"), str):
            names.add(body["name"])
        status, error = _answered(server, action, body)
        if action != "nothere" and len(body) == 1 and isinstance(next(iter(body.values())), dict):
            field = next(iter(body))  # an object where no field takes one: refused naming it (or the one missing)
            assert status == 400 and (f"'{field}'" in error or "the request has no" in error), (body, error)
    written = {p.name for p in folder.iterdir()} - {"run"}
    assert written <= names, written  # only a folder of the name Save got
    assert all((folder / n).is_dir() for n in written)


raw_bodies = st.one_of(
    st.binary(max_size=40),
    st.sampled_from([b"[" * 60000 + b"]" * 60000, b"[" * 30000, b'{"a":' * 20000, b"NaN", b"[1e400]", b'{"yaw": NaN}',
                     b"\xff\xfe", b"null", b"[]", b'"x"', b"0", b" ", b'{"name": "a\x00b"}', b'{"' + b"k" * 70000 + b'"}']),
)


@FUZZ
@given(action=st.sampled_from(["view", "orbit", "select", "edit", "save", "undo"]), raw=raw_bodies)
def test_a_body_that_is_no_json_object_is_refused_in_words(api, action, raw):
    server, _, _ = api
    status, error = _answered(server, action, raw=raw)
    if raw and raw.strip()[:1] != b"{":  # an empty body is an empty object
        assert status == 400, (raw[:40], error)


def test_the_editor_fuzz_saves_beside_the_run_and_nowhere_else(api):
    """The fuzz's check of writes, shown once: a Save of a good name writes that folder beside the
    run; names that are paths are refused."""
    server, folder, _ = api
    before = files_under(folder)
    for name in ("../outside", "a/b", "/tmp/x", ""):
        status, error = _answered(server, "save", {"name": name})
        assert status == 400 and "is not a folder name" in error
    assert files_under(folder) == before


def test_a_body_nested_deeper_than_the_parser_goes_is_refused():
    """Found by the fuzz: 60000 nested lists (within the body's size bound) ended the parser in a
    RecursionError, and the editor dropped the connection without an answer."""
    from vq_mitsuba.errors import InputError
    from vq_mitsuba.ui.server import parse_body

    for raw in (b"[" * 60000 + b"]" * 60000, b'{"a":' * 20000):
        with pytest.raises(InputError, match="the request body nests lists or objects too deep"):
            parse_body(raw)
