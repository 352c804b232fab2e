"""Every bundled preset (vq_mitsuba/presets/) fits a few steps on a tiny sphere through `vq-mitsuba fit --preset`: the
run is complete, its saved config holds the preset's values, and the discrete branch's materials
are written wherever the preset keeps that branch on."""

import json

import pytest
import torch
import yaml

from tiny_scene import write_sphere_capture
from vq_mitsuba.cli import main
from vq_mitsuba.config import CONFIG_VERSION, flat_keys, preset_path, presets

# Six steps; the discrete branch starts after vq.warmup_frac of them (step 2), so ranking runs.
SHORT = ["train.iterations=6", "train.batch_rays=128", "train.spp=2", "train.log_every=2",
         "train.checkpoint_every=1000", "vq.warmup_frac=0.3", "vq.rank_pixels=256"]


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("preset_sphere"), size=16, n_views=4, spp=8)


def test_the_presets_are_the_bundled_files():
    assert {"continuous", "demo", "ablation_no_ranking", "ablation_separate", "ablation_single_branch",
            "ablation_shared_light", "ablation_single_pass_ranking"} <= set(presets())


@pytest.mark.parametrize("name", presets())
def test_each_preset_fits_a_few_steps(name, capture, tmp_path):
    run = tmp_path / "run"
    args = ["fit", str(capture), "-o", str(run), "--preset", name, "--quiet"]
    for item in SHORT:
        args += ["--set", item]
    assert main(args) == 0
    for file in ("config.yaml", "checkpoint.pt", "fit.json", "run.json", "envmap.exr", "loss.png"):
        assert (run / file).is_file(), file
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["version"] == CONFIG_VERSION
    # The preset's own values (its ablation switch among them) are in the saved config, except
    # where the short-fit settings above replace them.
    preset = flat_keys(yaml.safe_load(preset_path(name).read_text()))
    overridden = {item.split("=")[0] for item in SHORT}
    assert preset and all(flat_keys(saved)[key] == value for key, value in preset.items() if key not in overridden)
    if name.startswith("ablation_"):
        assert saved["ablation"][name.removeprefix("ablation_")] is True
        assert sum(saved["ablation"].values()) == 1
    state = torch.load(run / "checkpoint.pt", weights_only=False)
    assert state["step"] == 6 and json.loads((run / "fit.json").read_text())["iterations"] == 6
    if saved["vq"]["enabled"]:
        materials = json.loads((run / "materials.json").read_text())
        assert 1 <= materials["num_materials"] <= saved["vq"]["num_codes"]
        if saved["ablation"]["no_ranking"]:
            assert materials["num_materials"] == saved["vq"]["num_codes"]
    else:
        assert name == "continuous" and not (run / "materials.json").exists()
