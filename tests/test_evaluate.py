"""`vq-mitsuba eval` end to end on a tiny generated scene (figures are meaningless at this size;
the test checks the contract: every block present, finite, in range, and the table printed)."""

import json
import math

import pytest

from vq_mitsuba.cli import main


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from vq_mitsuba.synthetic import make_scene

    return make_scene("demo", tmp_path_factory.mktemp("data") / "demo", resolution=16, n_train=4, n_test=2, spp=8,
                      progress=False)


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
    for v in (m["meanshift"]["0.3"], m["meanshift"]["0.5"]):
        assert 0.0 <= v["micro_f1"] <= 1.0 and v["num_materials_found"] >= 1


def test_eval_rejects_bad_bandwidths(tiny_dataset, capsys):
    with pytest.raises(SystemExit):
        main(["eval", "nowhere", "--gt", str(tiny_dataset), "--meanshift", "0.3,abc"])
    assert "comma-separated" in capsys.readouterr().err
