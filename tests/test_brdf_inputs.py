"""The BRDF inputs are declared once (vq_mitsuba/brdf.py): no other module spells an input's name,
and an input added to the declaration flows through scoring, the report, edits, the editor and a fit."""

import ast
import json
import re
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba import brdf

PACKAGE = Path(__file__).resolve().parent.parent / "vq_mitsuba"


def _spellings() -> dict[str, str]:
    """Every string that names an input: its name, its principled parameter, its Blender socket."""
    out = {}
    for i in brdf.INPUTS:
        out.update({i.name: i.name, i.principled: i.name, i.blender: i.name})
    return out


def test_no_module_outside_the_declaration_spells_an_input():
    spellings = _spellings()
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel == "brdf.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in spellings:
                found.append(f"vq_mitsuba/{rel}:{node.lineno}: {node.value!r} (use brdf.INPUTS or a brdf handle)")
    assert not found, "BRDF inputs spelled outside vq_mitsuba/brdf.py:\n" + "\n".join(found)


def test_the_editor_page_builds_its_controls_from_the_declaration():
    """The page's material controls come from the state's `inputs`: no static file names an input."""
    found = []
    for path in sorted((PACKAGE / "ui" / "static").iterdir()):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            found += [f"{path.name}:{n}: {name}" for name in brdf.NAMES if re.search(rf"\b{name}\b", line)]
    assert not found, "\n".join(found)


def test_handles_name_declared_inputs():
    assert {brdf.BASECOLOR, brdf.METALLIC, brdf.ROUGHNESS} <= set(brdf.NAMES)
    assert brdf.get(brdf.BASECOLOR).colour and not brdf.get(brdf.METALLIC).colour
    assert brdf.get("specular") is None
    assert len(set(brdf.NAMES)) == len(brdf.INPUTS) and brdf.CHANNELS == sum(i.channels for i in brdf.INPUTS)
    assert sorted(i.gltf_channel for i in brdf.INPUTS if i.gltf_channel is not None) == [1, 2]  # G, B


# --------------------------------------------------------------------------------------------
# A made-up fourth input, declared only in brdf.INPUTS

SHEEN = brdf.BrdfInput("sheen", 1, "sheen", "Sheen", high=0.8, step=0.05, default=0.1)


def _import_package():
    """Every module of the package, imported before the declaration is patched, so that none binds
    the patched tuple for good (a module first imported under the patch would keep it)."""
    import importlib
    import pkgutil

    import vq_mitsuba

    for info in pkgutil.walk_packages(vq_mitsuba.__path__, "vq_mitsuba."):
        if not info.name.endswith(("cycles_worker", "__main__")):
            importlib.import_module(info.name)


@pytest.fixture
def four_inputs(monkeypatch):
    import sys

    _import_package()
    inputs = (*brdf.INPUTS, SHEEN)
    patched = {"INPUTS": inputs, "NAMES": tuple(i.name for i in inputs), "CHANNELS": sum(i.channels for i in inputs)}
    original = {attr: getattr(brdf, attr) for attr in patched}
    for module in [m for name, m in sys.modules.items() if name.startswith("vq_mitsuba")]:
        for attr, value in patched.items():  # brdf's own and each `from vq_mitsuba.brdf import ...`
            if getattr(module, attr, None) is original[attr]:
                monkeypatch.setattr(module, attr, value)
    return inputs


def _views(n=2, h=6, w=5, seed=0):
    rng = np.random.default_rng(seed)
    gts, preds = [], []
    for _ in range(n):
        gt = {i.name: rng.uniform(0.0, 0.9, size=(h, w, 3) if i.colour else (h, w)) for i in brdf.INPUTS}
        gt["mask"] = np.ones((h, w), bool)
        pred = {k: v + 0.05 for k, v in gt.items() if k != "mask"}
        gts.append(gt), preds.append(pred)
    return preds, gts


def test_a_declared_input_is_scored_and_reported(four_inputs):
    from vq_mitsuba.eval import input_scores, report

    preds, gts = _views()
    masks = np.stack([g["mask"] for g in gts])
    scales = input_scores.alignment_scales(preds, gts, masks, "lstsq")
    assert set(scales) == {i.name for i in four_inputs if i.colour}
    rows = [input_scores.view_scores(p, g, g["mask"], scales) for p, g in zip(preds, gts)]
    assert {"sheen_psnr", "sheen_mae"} <= set(rows[0])
    means = input_scores.mean_scores(rows)
    assert list(means) == [i.name for i in four_inputs]  # one entry per declared input
    assert means["sheen"]["mae"] == pytest.approx(0.05, abs=1e-9)
    labels = [label for label, _, _ in input_scores.table_rows(means, "lstsq")]
    assert labels[-1] == "sheen (linear)" and len(labels) == len(four_inputs)
    metrics = {"alignment": {"method": "lstsq"}, "novel_view": {"psnr": 30.0, "ssim": 0.9},
               "relighting": {v: {"envs": {}, "mean": None} for v in ("albedo_scale", "image_scale")}, **means}
    assert "sheen (linear)" in [r[0] for r in report.table_rows(metrics)]


def test_a_declared_input_has_per_material_rows(four_inputs):
    from vq_mitsuba.eval.evaluate import per_material_scores

    preds, gts = _views(n=1)
    gts[0]["material"] = np.ones(gts[0]["mask"].shape, np.uint8)
    preds[0]["rgb"] = gts[0]["rgb"] = np.full(gts[0]["mask"].shape + (3,), 0.5)
    rows = per_material_scores(preds, gts, np.ones(3), {"materials": [{"id": 1, "name": "a"}]})
    assert rows[0]["sheen"] == pytest.approx(float(preds[0]["sheen"].mean()))
    assert rows[0]["sheen_true"] == pytest.approx(float(gts[0]["sheen"].mean()))
    assert rows[0]["sheen_mae"] == pytest.approx(0.05, abs=1e-9)


def test_a_declared_input_is_edited_in_its_range_and_offered_by_the_editor(four_inputs):
    import torch

    from vq_mitsuba.models.material_edits import Change, apply_change, check_change
    from vq_mitsuba.ui.session import editor_inputs

    sheen = next(x for x in editor_inputs() if x["name"] == "sheen")
    assert sheen == {"name": "sheen", "channels": 1, "low": 0.0, "high": 0.8, "step": 0.05, "default": 0.1}
    assert [x["name"] for x in editor_inputs()] == [i.name for i in four_inputs]
    assert check_change(Change("set", "sheen", 0.5)).value == 0.5
    with pytest.raises(ValueError, match=r"sheen must lie in \[0, 0.8\]"):
        check_change(Change("set", "sheen", 0.9))
    with pytest.raises(ValueError, match="hue_shift acts on"):
        check_change(Change("hue_shift", "sheen", 10.0))
    values = {"sheen": torch.tensor([0.2, 0.4])}
    apply_change(values, Change("scale", "sheen", 3.0), torch.tensor([True, True]))
    assert values["sheen"].tolist() == pytest.approx([0.6, 0.8])  # clamped to its high end


def test_a_declared_input_reaches_the_synthetic_scene_writers(four_inputs):
    from vq_mitsuba.data.formats.mitsuba_xml import _bsdf_xml

    xml = _bsdf_xml({"name": "m", "base_color": [0.1, 0.2, 0.3], "metallic": 0.0, "roughness": 0.5, "sheen": 0.25})
    assert '<float name="sheen" value="0.25"/>' in xml


def test_a_declared_input_with_its_decoder_is_fitted(four_inputs, monkeypatch, tmp_path):
    """The declaration and a decoder head are all a fit needs: Mitsuba's principled BSDF takes the
    input by its parameter, its gradient reaches the head, and both branches' materials carry it."""
    import torch

    from tiny_scene import write_sphere_capture
    from vq_mitsuba.config import load_config
    from vq_mitsuba.engine.pipeline import fit
    from vq_mitsuba.models import fields
    from vq_mitsuba.run.run_dir import RunDir

    grads = []
    init, forward = fields.BRDFDecoder.__init__, fields.BRDFDecoder.forward

    def with_head(self, cfg):
        init(self, cfg)
        self.sheen = fields.SkipMLP(cfg.latent, cfg.decoder_hidden, 1, n_layers=3, skip_at=2)
        for p in self.sheen.parameters():
            p.register_hook(lambda g: grads.append(float(g.abs().sum())))

    monkeypatch.setattr(fields.BRDFDecoder, "__init__", with_head)
    monkeypatch.setattr(fields.BRDFDecoder, "forward",
                        lambda self, z: {**forward(self, z), "sheen": SHEEN.high * torch.sigmoid(self.sheen(z))[..., 0]})
    xml = write_sphere_capture(tmp_path / "cap", size=16, n_views=4, spp=8)
    cfg = load_config(None, ["train.batch_rays=64", "residual.iterations=0", "train.iterations=40",
                             "vq.warmup_frac=0.1"])
    fit(xml, tmp_path / "run", cfg)
    assert grads and max(grads) > 0  # shading differentiates the new input
    materials = json.loads((tmp_path / "run" / "materials.json").read_text())["materials"]
    assert all(0.0 <= m["sheen"] <= SHEEN.high for m in materials)
    fitted = RunDir(tmp_path / "run").load()
    with torch.no_grad():
        out = fitted.model(torch.zeros(4, 3, device=fitted.model.center.device))
    assert out["sheen"].shape == (4,)
