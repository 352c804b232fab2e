"""The discrete branch end to end: material count and segmentation on a two-material scene."""

import json

import pytest

from vq_mitsuba.config import load_config
from vq_mitsuba.engine.pipeline import fit


@pytest.mark.slow
def test_two_material_scene_gives_two_materials(tmp_path):
    from vq_mitsuba.eval.evaluate import evaluate
    from vq_mitsuba.synthetic.mitsuba_scenes import make_scene

    data = make_scene("demo", tmp_path / "demo", resolution=48, n_train=16, n_test=3, spp=64)
    cfg = load_config(None, ["vq.enabled=true", "train.iterations=1200", "train.batch_rays=1024", "render.spp=32"])
    fit(data / "scene.xml", tmp_path / "run", cfg)
    materials = json.loads((tmp_path / "run" / "materials.json").read_text())
    assert materials["num_materials"] == 2, materials["err_k"]
    m = evaluate(tmp_path / "run", data)
    assert m["segmentation"]["micro_f1"] >= 0.9
    assert m["segmentation"]["macro_f1"] >= 0.8
