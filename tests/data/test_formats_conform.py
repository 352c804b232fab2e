"""Every registered capture format keeps the format contract (`vq_mitsuba.data.formats`): its
declared members, and on a capture its own writer made: the folder resolves to it, its `detect`
takes its own capture and no other format's, its cameras and its loaded capture agree."""

import ast
import inspect
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba.data.captures import resolve_capture_path
from vq_mitsuba.data.formats import FORMATS, CaptureFormat, PosedFormat, UnposedFormat, format_of

# Where make-scene --photo-formats puts each posed format's copy of the training views.
FOLDERS = {"nerf_synthetic": "", "mitsuba_xml": "scene.xml", "idr": "neus", "colmap": "colmap",
           "nerfstudio": "nerfstudio", "llff": "llff"}


def _name(fmt) -> str:
    return fmt.__name__.rsplit(".", 1)[1]


@pytest.mark.parametrize("fmt", FORMATS, ids=_name)
def test_each_format_declares_the_contract(fmt):
    assert isinstance(fmt, CaptureFormat)
    assert isinstance(fmt.KIND, str) and isinstance(fmt.POSED, bool)
    assert isinstance(fmt.SUFFIXES, tuple) and all(s.startswith(".") and s == s.lower() for s in fmt.SUFFIXES)
    assert isinstance(fmt.FOLDER_FILES, tuple) and all(isinstance(n, str) for n in fmt.FOLDER_FILES)
    assert list(inspect.signature(fmt.detect).parameters) == ["source"]
    if fmt.POSED:
        assert isinstance(fmt, PosedFormat)
        assert len(inspect.signature(fmt.cameras).parameters) == 1
        assert list(inspect.signature(fmt.has_geometry).parameters) in (["source"], ["xml"])
        assert list(inspect.signature(fmt.load).parameters)[1:] == ["mesh_arg", "shrink", "cache_dir"]
        assert all(f is None or len(inspect.signature(f).parameters) == 1 for f in (fmt.points, fmt.sphere))
    else:
        assert isinstance(fmt, UnposedFormat) and not hasattr(fmt, "load")
        assert isinstance(fmt.NOUN, str) and isinstance(fmt.SEQUENTIAL, bool)


def test_the_registry_names_each_format_once():
    assert len({_name(f) for f in FORMATS}) == len(FORMATS)
    assert set(FOLDERS) == {_name(f) for f in FORMATS if f.POSED}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from vq_mitsuba.synthetic.mitsuba_scenes import make_scene

    out = tmp_path_factory.mktemp("formats") / "demo"
    make_scene("demo", out, resolution=16, n_train=5, n_test=1, spp=4, photo_formats=True)
    return out


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f.POSED], ids=_name)
def test_each_posed_format_reads_its_own_capture(fmt, dataset):
    source = resolve_capture_path(dataset / FOLDERS[_name(fmt)])
    assert format_of(source) is fmt
    for other in FORMATS:
        if other is not fmt and other.POSED:
            other_source = resolve_capture_path(dataset / FOLDERS[_name(other)])
            assert not fmt.detect(other_source) or format_of(other_source) is not fmt
    # The scene XML has its shapes; another capture has geometry when its folder holds the mesh.
    folder = source if source.is_dir() else source.parent
    assert fmt.has_geometry(source) == (fmt.KIND == "xml" or (folder / "mesh.ply").is_file())
    cameras, world = fmt.cameras(source)
    assert len(cameras) == 5 and isinstance(world, str)
    capture = fmt.load(source, None, None, None)
    assert len(capture.cameras) == 5 and capture.images.shape[:3] == (5, 16, 16)
    assert np.isfinite(capture.images).all()
    if fmt.points is not None:
        points = fmt.points(source)
        assert points is None or (points[0].ndim == 2 and points[0].shape[1] == 3)
    if fmt.sphere is not None:
        centre, radius, given_by = fmt.sphere(source)
        assert np.shape(centre) == (3,) and radius > 0


def test_no_module_outside_the_formats_branches_on_a_format():
    """Code outside data/formats/ never compares a capture's KIND with a format's name: what a
    format means is asked of its module (POSED, NOUN, has_geometry, ...)."""
    import ast

    package = Path(__file__).resolve().parents[2] / "vq_mitsuba"
    kinds = {fmt.KIND for fmt in FORMATS}
    found = []
    for path in package.rglob("*.py"):
        if "formats" in path.relative_to(package).parts[:2]:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare):
                consts = [c for c in ast.walk(node) if isinstance(c, ast.Constant) and c.value in kinds]
                names = [n for n in ast.walk(node) if isinstance(n, (ast.Name, ast.Attribute))
                         and "kind" in (n.id if isinstance(n, ast.Name) else n.attr).lower()]
                if consts and names:
                    found.append(f"{path.relative_to(package)}:{node.lineno}")
    assert not found, found


def _strings_outside_docstrings(tree):
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return [node for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings]


def test_no_module_outside_the_formats_spells_a_format_layout():
    """The files that make a capture (each format's FOLDER_FILES, a NeRF-synthetic split's file, a
    COLMAP model's layout) are spelled in data/formats/ alone, docstrings aside: other modules take
    them from the format modules. The exports write files of formats of their own (export/)."""
    from vq_mitsuba.data.formats import colmap, nerf_synthetic

    layout = {name for fmt in FORMATS for name in fmt.FOLDER_FILES}
    layout |= {nerf_synthetic.SPLIT_FILE.split("{")[0], f"{colmap.MODEL.parts[0]}/", "points3D.bin", "cameras.bin",
               "images.bin"}
    package = Path(__file__).resolve().parents[2] / "vq_mitsuba"
    found = []
    for path in package.rglob("*.py"):
        where = path.relative_to(package).parts
        if where[:2] == ("data", "formats") or where[0] == "export":
            continue
        for node in _strings_outside_docstrings(ast.parse(path.read_text())):
            found += [f"{path.relative_to(package)}:{node.lineno}: {name}" for name in layout if name in node.value]
    assert not found, found
