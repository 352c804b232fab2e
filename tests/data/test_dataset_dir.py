"""DatasetDir: the one place that names a make-scene dataset's files."""

import ast
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.errors import InputError

PACKAGE = Path(__file__).resolve().parents[2] / "vq_mitsuba"
# Names a dataset shares with other layouts, which their own modules spell: the capture formats'
# files (transforms_train.json, scene.xml, mesh.ply, images/), glTF's "meshes", the renderer's
# "relit" maps, the UI's "envmaps", a split called "train" and the Cycles worker's job.json.
SHARED = {DatasetDir.TRANSFORMS_TRAIN, DatasetDir.SCENE_XML, DatasetDir.MESH, DatasetDir.IMAGES, DatasetDir.MESHES,
          DatasetDir.RELIT, DatasetDir.ENVMAPS, DatasetDir.TRAIN_ENVMAP, DatasetDir.CYCLES_JOB}
# Paths inside a dataset begin with one of its folders.
FOLDERS = tuple(f"{d}/" for d in (DatasetDir.GT, DatasetDir.RELIT, DatasetDir.ENVMAPS, DatasetDir.MESHES)) + \
    (f"./{DatasetDir.IMAGES}/",)


def _docstrings(tree) -> set[int]:
    nodes = [tree] + [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                                   ast.ClassDef))]
    return {id(n.body[0].value) for n in nodes if n.body and isinstance(n.body[0], ast.Expr)
            and isinstance(n.body[0].value, ast.Constant)}


def test_only_dataset_dir_names_dataset_files():
    """scene.json, transforms_test.json, scene_test.xml, gt/, the make-scene mark and the Cycles work
    folder are named once, in DatasetDir, and no module spells a path inside a dataset's folders."""
    names = {v for k, v in vars(DatasetDir).items() if k.isupper() and isinstance(v, str)} - SHARED
    assert {"scene.json", "transforms_test.json", "scene_test.xml", "gt", ".make-scene-incomplete"} <= names
    found = []
    for path in PACKAGE.rglob("*.py"):
        rel = str(path.relative_to(PACKAGE))
        if path.name in ("dataset_dir.py", "cycles_worker.py"):  # the worker runs inside Blender, reads its job
            continue
        tree = ast.parse(path.read_text())
        skip = _docstrings(tree)
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Constant) and isinstance(node.value, str)) or id(node) in skip:
                continue
            if node.value in names or node.value.startswith(FOLDERS):
                found.append((rel, node.lineno, node.value))
    assert not found, found


def test_paths_of_a_dataset(tmp_path):
    d = DatasetDir(tmp_path)
    assert d.image("test_000") == tmp_path / "images" / "test_000"
    assert d.image("test_000", "sunset") == tmp_path / "relit" / "sunset" / "test_000"
    assert d.gt("test_000", "basecolor") == tmp_path / "gt" / "test_000_basecolor.exr"
    assert d.gt("test_000", "alpha") == tmp_path / "gt" / "test_000_alpha.png"
    with pytest.raises(ValueError):
        d.gt("test_000", "albedo")
    assert DatasetDir.envmap_file("train") == "envmaps/train.exr" and d.envmap("x") == tmp_path / "envmaps" / "x.exr"
    assert DatasetDir.shape_file("torus") == "meshes/torus.ply" and DatasetDir.frame_file("a") == "./images/a"
    assert d.info_path == tmp_path / "scene.json" and d / "mesh.ply" == tmp_path / "mesh.ply"


def test_find_refuses_what_is_not_a_whole_dataset(tmp_path):
    with pytest.raises(InputError, match="dataset folder not found"):
        DatasetDir.find(tmp_path / "none")
    (tmp_path / "scene.json").write_text("{}")
    with pytest.raises(InputError, match="transforms_test.json: not a dataset"):
        DatasetDir.find(tmp_path)
    (tmp_path / "transforms_test.json").write_text("{}")
    assert DatasetDir.find(tmp_path / "scene.json").dir == tmp_path


def test_prepare_empties_an_earlier_dataset_only(tmp_path):
    d = DatasetDir(tmp_path)
    d.prepare()
    assert all((tmp_path / sub).is_dir() for sub in DatasetDir.SUBDIRS)
    (tmp_path / "images" / "old.exr").write_bytes(b"")
    d.prepare()  # no scene.json, no mark: not a dataset of make-scene, nothing removed
    assert (tmp_path / "images" / "old.exr").is_file()
    d.mark_incomplete()
    assert (tmp_path / DatasetDir.INCOMPLETE).is_file()
    d.prepare()
    assert not (tmp_path / "images" / "old.exr").exists()
    d.write_info({"name": "demo"})
    d.mark_complete()
    assert d.is_dataset() and not (tmp_path / DatasetDir.INCOMPLETE).exists() and d.info() == {"name": "demo"}


def test_views_and_ground_truth_are_written_in_the_layout(tmp_path):
    d = DatasetDir(tmp_path)
    d.prepare()
    rgba = np.zeros((4, 5, 4), np.float32)
    rgba[1:3, 1:4] = [0.2, 0.4, np.nan, 1.0]
    d.write_view("v", rgba)
    d.relit_dir("sun").mkdir()
    d.write_view("v", rgba, "sun")
    gt = {k: np.full((4, 5, 3) if k in ("basecolor", "normal") else (4, 5), 0.5, np.float32)
          for k in ("basecolor", "metallic", "roughness", "normal", "alpha")}
    gt["material"] = np.ones((4, 5), np.uint8)
    d.write_gt("v", gt)
    written = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
    assert written == sorted(["images/v.exr", "images/v.png", "relit/sun/v.exr", "relit/sun/v.png"] +
                             [str(d.gt("v", k).relative_to(tmp_path)) for k in DatasetDir.GT_EXR + DatasetDir.GT_PNG])


def test_info_is_checked_and_relight_envs_found(tmp_path):
    d = DatasetDir(tmp_path)
    d.info_path.write_text('{"relight": [{"name": "../up", "file": "envmaps/x.exr"}]}')
    with pytest.raises(InputError, match=r"relight\[0\] must be"):
        d.info()
    d.info_path.write_text("[]")
    with pytest.raises(InputError, match="expected a JSON object"):
        d.info()
    (tmp_path / "relit" / "sunset").mkdir(parents=True)
    with pytest.raises(InputError, match="envmap of relighting condition 'sunset' missing"):
        d.relight_envs({})
    (tmp_path / "envmaps").mkdir()
    (tmp_path / "envmaps" / "sunset.exr").write_bytes(b"")
    assert d.relight_envs({}) == [("sunset", tmp_path / "envmaps" / "sunset.exr")]
