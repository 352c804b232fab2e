"""The method end to end on a known answer: three materials must give M = 3 and a segmentation
that matches the truth, with the defaults (both branches, dropout ranking)."""

import numpy as np
import torch

from tiny_scene import three_material_ids
from vq_mitsuba.data.captures import load_capture
from vq_mitsuba.run.run_dir import RunDir
from vq_mitsuba.eval.metrics import segmentation_scores
from vq_mitsuba.render.views import Renderer


def test_three_materials_give_m_3(three_materials):
    _, run = three_materials
    materials = run.materials()
    assert materials["num_materials"] == 3, materials["err_k"]
    assert (run / RunDir.ERR_PLOT).is_file() and (run / RunDir.SHEET).is_file()
    # The ranked materials are the three true ones (one each), told apart by metallic and colour.
    found = sorted((m["metallic"] > 0.5, int(np.argmax(m["basecolor"]))) for m in materials["materials"])
    assert found == [(False, 0), (False, 2), (True, 0)], materials["materials"]


def test_three_materials_segment_the_views(three_materials):
    capture_path, run = three_materials
    capture = load_capture(capture_path)
    fitted = run.load()
    renderer = Renderer(fitted)
    preds, gts = [], []
    for cam in capture.cameras:
        images = renderer.render(cam, spp=4, aa=1)
        from vq_mitsuba.data.cameras import camera_rays

        hits = renderer.scene.trace(*camera_rays(cam))
        gt = np.zeros(cam.width * cam.height, np.int64)
        valid = hits.valid.cpu().numpy()
        gt[valid] = three_material_ids(hits.position[hits.valid].cpu().numpy())
        preds.append(images["material"].reshape(-1))
        gts.append(gt)
    scores = segmentation_scores(np.concatenate(preds), np.concatenate(gts))
    assert scores["micro_f1"] >= 0.95, scores
    assert torch.is_tensor(fitted.discrete.num_materials) and fitted.num_materials == 3
