"""`vq-mitsuba eval` end to end on a tiny generated scene (figures are meaningless at this size;
the test checks the contract: every block present, finite, in range, and the table printed)."""

import json
import math

import pytest

from vq_mitsuba.cli import main


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from vq_mitsuba.synthetic.mitsuba_scenes import make_scene

    return make_scene("demo", tmp_path_factory.mktemp("data") / "demo", resolution=16, n_train=4, n_test=2, spp=8)


def test_eval_writes_every_block(tiny_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["fit", str(tiny_dataset / "scene.xml"), "-o", str(run), "--quiet", "--set", "vq.enabled=true",
                 "--set", "train.iterations=4", "--set", "train.batch_rays=128", "--set", "vq.warmup_frac=0.25"]) == 0
    out = tmp_path / "metrics.json"
    assert main(["eval", str(run), "--gt", str(tiny_dataset), "--spp", "4", "--quiet", "-o", str(out),
                 "--meanshift", "0.3,0.5"]) == 0
    text = capsys.readouterr().out
    assert "novel view" in text and "MeanShift baseline (bandwidth 0.3)" in text
    m = json.loads(out.read_text())
    assert m["n_views"] == 2 and math.isfinite(m["novel_view"]["psnr"]) and math.isfinite(m["basecolor"]["psnr"])
    assert set(m["relighting"]["albedo_scale"]["envs"]) == {"sunset", "studio"}
    assert "discrete: basecolor" in text and math.isfinite(m["discrete_branch"]["basecolor"]["psnr"])
    seg = m["segmentation"]
    assert 0.0 <= seg["micro_f1"] <= 1.0 and seg["num_materials_true"] == 2 and 1 <= seg["num_materials_found"] <= 8
    assert set(k for k in m["meanshift"] if k != "features") == {"0.3", "0.5"}
    assert [row["id"] for row in m["per_material"]] == [1, 2] and "per material" in text
    for v in (m["meanshift"]["0.3"], m["meanshift"]["0.5"]):
        assert 0.0 <= v["micro_f1"] <= 1.0 and v["num_materials_found"] >= 1


def test_eval_rejects_bad_bandwidths(tiny_dataset, capsys):
    with pytest.raises(SystemExit):
        main(["eval", "nowhere", "--gt", str(tiny_dataset), "--meanshift", "0.3,abc"])
    assert "comma-separated" in capsys.readouterr().err


def test_per_material_scores_name_the_wrong_material():
    """Hand-made maps: material 2's metallic is fitted as 1 instead of 0, material 1 is exact."""
    import numpy as np

    from vq_mitsuba.eval.evaluate import per_material_scores

    ids = np.array([[1, 1, 2], [2, 0, 2]])
    mask = ids > 0
    gt = {"mask": mask, "material": ids, "rgb": np.full((2, 3, 3), 0.25), "basecolor": np.full((2, 3, 3), 0.5),
          "metallic": np.zeros((2, 3)), "roughness": np.where(ids == 1, 0.8, 0.2)}
    pred = {k: np.array(v, dtype=float) for k, v in gt.items() if k not in ("mask", "material")}
    pred["basecolor"] = pred["basecolor"] / 2  # alignment scale 2 undoes this
    pred["metallic"] = np.where(ids == 2, 1.0, 0.0)[..., None]
    pred["roughness"] = pred["roughness"][..., None]
    gt["metallic"], gt["roughness"] = gt["metallic"][..., None], gt["roughness"][..., None]
    meta = {"materials": [{"id": 1, "name": "red"}, {"id": 2, "name": "plastic"}]}
    rows = per_material_scores([pred], [gt], np.full(3, 2.0), meta)
    assert [(r["id"], r["name"], r["pixels"]) for r in rows] == [(1, "red", 2), (2, "plastic", 3)]
    assert rows[0]["metallic_mae"] == 0.0 and rows[1]["metallic_mae"] == 1.0
    assert rows[1]["metallic"] == 1.0 and rows[1]["metallic_true"] == 0.0
    assert rows[0]["roughness"] == pytest.approx(0.8) and rows[1]["roughness_true"] == pytest.approx(0.2)
    assert rows[0]["basecolor"] == pytest.approx([0.5] * 3) and math.isinf(rows[0]["novel_view_psnr"])
    assert per_material_scores([pred], [{k: v for k, v in gt.items() if k != "material"}], np.ones(3), meta) is None
    # A view without material 2 (and 2-D scalar maps) adds no pixels to it.
    gt1 = dict(gt, material=np.where(ids == 2, 1, ids), metallic=gt["metallic"][..., 0])
    pred1 = dict(pred, metallic=pred["metallic"][..., 0])
    rows = per_material_scores([pred, pred1], [gt, gt1], np.full(3, 2.0), meta)
    assert [r["pixels"] for r in rows] == [2 + 5, 3]


def test_coverage_scores_separate_missed_pixels_from_material_error():
    """Hand-made view: 4 foreground pixels, the prediction covers 3 of them plus 1 background
    pixel; its basecolor is exact where it covers and empty (0) where it misses."""
    import numpy as np

    from vq_mitsuba.eval.evaluate import coverage_scores

    mask = np.array([[True, True, True, True, False, False]])
    alpha = np.array([[1.0, 1.0, 0.6, 0.2, 0.9, 0.0]])
    gt = np.full((1, 6, 3), 0.5)
    pred = np.where((alpha >= 0.5)[..., None], gt, 0.0)
    s = coverage_scores(alpha, pred, gt, mask)
    assert s["coverage_iou"] == pytest.approx(3 / 5)  # 3 covered foreground of 5 in the union
    assert math.isinf(s["basecolor_psnr_covered"])
    pred[0, 1] = 0.25  # a material error on a covered pixel lowers it
    assert math.isfinite(coverage_scores(alpha, pred, gt, mask)["basecolor_psnr_covered"])


class _GroundTruthPredictor:
    """A predictor whose renders are the dataset's own ground truth: a perfect method."""

    world = "blender"
    default_spp, default_aa = 1, 1

    def __init__(self, root):
        from vq_mitsuba.data.imageio import read_image
        from vq_mitsuba.eval.evaluate import load_ground_truth, relight_envs

        self.root = root
        meta = json.loads((root / "scene.json").read_text())
        self.num_materials = len(meta["materials"])
        self.envs = [(name, read_image(path)[0]) for name, path in relight_envs(root, meta)]
        self.load = load_ground_truth

    def renderer(self, envmap=None):
        import numpy as np

        name = None if envmap is None else next(n for n, e in self.envs if np.array_equal(e, envmap))
        return _GroundTruthRenderer(self, name)


class _GroundTruthRenderer:
    def __init__(self, predictor, env_name):
        self.p, self.env_name = predictor, env_name

    def render(self, camera, spp=None, aa=None, seed=0):
        from vq_mitsuba.data.imageio import read_image

        gt = self.p.load(self.p.root, camera.name)
        out = {"alpha": gt["mask"].astype("float32"), "basecolor": gt["basecolor"], "metallic": gt["metallic"],
               "roughness": gt["roughness"], "normal": gt["normal"], "material": gt["material"], "rgb": gt["rgb"]}
        if self.env_name is not None:
            out["rgb"] = read_image(self.p.root / "relit" / self.env_name / f"{camera.name}.exr")[0][..., :3]
        return out


def test_ground_truth_scored_as_the_prediction_is_perfect(tiny_dataset):
    """Known answer: the dataset's own maps as the prediction give F1 = 1, alignment scales of 1,
    zero metallic/roughness error and unbounded PSNR everywhere."""
    from vq_mitsuba.eval.evaluate import evaluate_predictor

    m = evaluate_predictor(_GroundTruthPredictor(tiny_dataset), tiny_dataset, meanshift_bandwidths=())
    assert m["alignment"]["scales"] == pytest.approx([1.0, 1.0, 1.0], abs=1e-6)
    seg = m["segmentation"]
    assert seg["micro_f1"] == 1.0 and seg["macro_f1"] == 1.0 and seg["num_materials_found"] == 2
    assert m["metallic"]["mae"] == 0.0 and m["roughness"]["mae"] == 0.0
    assert m["normal"]["mae_deg"] < 0.1
    for psnr in (m["novel_view"]["psnr"], m["basecolor"]["psnr"], m["metallic"]["psnr"], m["roughness"]["psnr"],
                 m["relighting"]["albedo_scale"]["mean"]["psnr"]):
        assert psnr == math.inf or psnr > 80
    assert m["novel_view"]["ssim"] == pytest.approx(1.0)


def test_eval_reports_novel_view_with_and_without_the_residual(tiny_dataset, tmp_path, capsys):
    """Both figures from one render: the physically based one is what the same run without its
    residual.pt scores, the other is the render with the residual added."""
    import shutil

    from vq_mitsuba.run.run_dir import RunDir

    run = tmp_path / "run"
    assert main(["fit", str(tiny_dataset / "scene.xml"), "-o", str(run), "--quiet", "--set", "train.iterations=4",
                 "--set", "train.batch_rays=128", "--set", "residual.iterations=30"]) == 0
    # so short a fit's residual may keep the zero field (a gain under MIN_GAIN_DB): a field that adds
    # a constant, written as the fit writes its own
    import torch

    state = torch.load(run / RunDir.RESIDUAL, map_location="cpu", weights_only=False)
    last = max((k for k in state["field"] if k.startswith("mlp.") and k.endswith(".bias")),
               key=lambda k: int(k.split(".")[1]))
    state["field"][last] = state["field"][last] + 0.05
    RunDir(run).save_residual(state["field"], state["step"])
    bare = tmp_path / "bare"
    shutil.copytree(run, bare)
    (bare / RunDir.RESIDUAL).unlink()
    m = {}
    for name in ("run", "bare"):
        out = tmp_path / f"{name}.json"
        assert main(["eval", str(tmp_path / name), "--gt", str(tiny_dataset), "--spp", "4", "--quiet", "-o", str(out),
                     "--meanshift", "none"]) == 0
        m[name] = json.loads(out.read_text())
    assert "novel view + residual" in capsys.readouterr().out
    with_r, without = m["run"], m["bare"]
    assert without["novel_view_residual"] is None
    assert with_r["novel_view"]["psnr"] == pytest.approx(without["novel_view"]["psnr"], abs=1e-9)
    assert math.isfinite(with_r["novel_view_residual"]["psnr"])
    assert with_r["novel_view_residual"]["psnr"] != with_r["novel_view"]["psnr"]
    assert all("novel_view_residual_psnr" in row for row in with_r["per_view"])
    # the relighting renders leave the residual out: the same figures as the run without it
    assert with_r["relighting"]["image_scale"]["mean"]["psnr"] == \
        pytest.approx(without["relighting"]["image_scale"]["mean"]["psnr"], abs=1e-9)
