"""RunDir: every file of a run written and read in one place, with a format version."""

import json

import numpy as np
import pytest
import torch
import trimesh

from vq_mitsuba.config import load_config
from vq_mitsuba.run.run_dir import FORMAT_VERSION, RunDir
from vq_mitsuba.errors import InputError
from vq_mitsuba.models.fields import ContinuousMaterial, EnvironmentMap
from vq_mitsuba.models.vq import DiscreteBranch


def _write_run(path, cfg):
    run = RunDir(path)
    run.create()
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    run.write_config(cfg)
    run.write_mesh(mesh)
    run.write_info({"capture": "/nowhere/scene.xml", "world": "blender", "envmap_to_world": np.eye(4).tolist()})
    bbox = torch.tensor(np.asarray(mesh.bounds), dtype=torch.float32)
    torch.manual_seed(0)
    model = ContinuousMaterial(cfg.field, bbox[0], bbox[1])
    discrete = DiscreteBranch(cfg.field, cfg.vq.num_codes, cfg.vq.decay, cfg.vq.commitment)
    discrete.initialised.fill_(True)
    discrete.num_materials.fill_(3)
    env = EnvironmentMap(4, 1.5)
    run.save_state({"model": model.state_dict(), "discrete": discrete.state_dict(), "envmap": env.state_dict(),
                    "envmap_fixed": None, "step": 17})
    run.write_materials({"num_materials": 3, "err_k": [0.3, 0.2, 0.1]})
    run.write_fit_summary({"iterations": 17, "seconds": 2.0})
    return run, model, env


def test_round_trip(tmp_path):
    cfg = load_config(None, ["field.hidden=32", "field.latent=8", "vq.num_codes=5", "render.spp=12"])
    run, model, env = _write_run(tmp_path / "run", cfg)
    again = RunDir(tmp_path / "run")
    assert again.info()["format"] == FORMAT_VERSION
    assert again.config() == cfg
    fitted = again.load()
    assert fitted.step == 17 and fitted.world == "blender" and fitted.num_materials == 3
    np.testing.assert_allclose(fitted.envmap, np.full((4, 8, 3), 1.5), rtol=1e-6)
    np.testing.assert_array_equal(fitted.envmap_to_world, np.eye(4))
    x = torch.rand(10, 3) - 0.5
    with torch.no_grad():
        for key in ("basecolor", "metallic", "roughness"):
            torch.testing.assert_close(fitted.model(x)[key], model(x)[key])
    assert again.materials()["err_k"] == [0.3, 0.2, 0.1]
    assert again.fit_summary()["iterations"] == 17
    assert len(fitted.mesh.faces) == 320


def test_unknown_format_version_is_refused(tmp_path):
    run, _, _ = _write_run(tmp_path / "run", load_config(None, ["field.hidden=16", "field.latent=4"]))
    info = json.loads((run / RunDir.INFO).read_text())
    info["format"] = FORMAT_VERSION + 1
    (run / RunDir.INFO).write_text(json.dumps(info))
    with pytest.raises(InputError, match=f"format {FORMAT_VERSION + 1}"):
        RunDir(run.dir).load()
    del info["format"]
    (run / RunDir.INFO).write_text(json.dumps(info))
    with pytest.raises(InputError, match="run.json"):
        RunDir(run.dir).info()


def test_a_folder_without_a_run_is_named(tmp_path):
    with pytest.raises(InputError, match="run.json missing"):
        RunDir(tmp_path).load()


def test_parsed_once_but_each_load_has_its_own_config(tmp_path, monkeypatch):
    """run.json and config.yaml are read once per RunDir; a caller that changes its FittedModel's
    config (a preview without the bounce) changes no later load of the same run."""
    cfg = load_config(None, ["field.hidden=16", "field.decoder_hidden=16", "vq.num_codes=4"])
    run = RunDir(_write_run(tmp_path / "run", cfg)[0].dir)
    first = run.load()
    first.cfg.train.bounces = 0
    reads = []
    monkeypatch.setattr(RunDir, "saved_config", lambda self: reads.append(1) or {})
    second = run.load()
    assert second.cfg.train.bounces == cfg.train.bounces == 1
    assert reads == []  # the cached parse, not the file again
    assert run.info() is run.info()
    written = {**run.info(), "n_views": 7}
    run.write_info({k: v for k, v in written.items() if k != "format"})
    assert RunDir(run.dir).info()["n_views"] == 7 and run.info()["n_views"] == 7
