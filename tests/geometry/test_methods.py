"""The registry of geometry methods (`vq_mitsuba.geometry.methods`): a method registered by a test
runs through the geometry stage and the fit's pipeline without any of NeuS's code, the CLI offers
it, and a name nobody registered is refused with the names that are."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba.config import load_config
from vq_mitsuba.data.imageio import write_png
from vq_mitsuba.geometry import methods
from vq_mitsuba.geometry.methods import Framing, Reconstruction
from vq_mitsuba.run.run_dir import RunDir

TOY_STATE = "toy_state.json"


def _write_capture(root: Path, size: int = 8) -> Path:
    """A NeRF json capture without geometry: three views of the origin, RGBA PNGs (all opaque)."""
    (root / "train").mkdir(parents=True)
    frames = []
    for k, position in enumerate(([0.0, -3.0, 1.0], [3.0, 0.0, 1.0], [0.0, 3.0, 1.5])):
        back = np.asarray(position) / np.linalg.norm(position)  # OpenGL cameras look along -Z
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, position
        write_png(root / "train" / f"r_{k}.png", np.full((size, size, 3), 128, np.uint8), alpha=np.ones((size, size)))
        frames.append({"file_path": f"./train/r_{k}", "transform_matrix": c2w.tolist()})
    path = root / "transforms_train.json"
    path.write_text(json.dumps({"camera_angle_x": 0.6, "frames": frames}))
    return path


class Toy:
    """A geometry method for tests: a sphere of radius 0.5 at the origin, whatever the capture shows."""

    label = "Toy"
    files = (TOY_STATE,)
    seed_key = None
    masks_from_mesh = False

    def reconstruct(self, source, run, cfg, resume=False) -> Reconstruction:
        import trimesh

        views = len(source.load("train").cameras)
        run.create()
        state = run / TOY_STATE
        resumed = resume and state.is_file()
        state.write_text(json.dumps({"views": views}))
        return Reconstruction(trimesh.creation.icosphere(subdivisions=2, radius=0.5), {"views": views},
                              masks_from_mesh=self.masks_from_mesh, framing=Framing((0.0, 0.0, 0.0), 0.5, "toy"),
                              scores={"views": views}, files=(state,), resumed=resumed)

    def report(self, summary: dict) -> list[str]:
        return [f"Toy: a sphere for {summary['views']} views"] if "views" in summary else []


@pytest.fixture
def toy(monkeypatch):
    """The Toy method registered as "toy" (removed afterwards), NeuS's reconstruction failing the test
    if reached."""
    from vq_mitsuba.geometry.neus.method import NeuSMethod

    def no_neus(*args, **kwargs):
        raise AssertionError("NeuS ran")

    monkeypatch.setattr(NeuSMethod, "reconstruct", no_neus)
    registered = methods.register("toy")(type("ToyMethod", (Toy,), {}))
    yield methods.get("toy")
    methods.unregister("toy")
    assert registered.name == "toy" and "toy" not in methods.names()


def test_neus_is_the_first_method_and_the_default():
    assert methods.names()[0] == methods.DEFAULT == "neus"
    neus = methods.get("neus")
    assert neus.label == "NeuS" and neus.files == ("neus.pt",) and neus.seed_key == "neus.seed"
    assert methods.fit_modes() == ("auto", "neus", "given")
    assert "neus.pt" in RunDir.markers() and "neus.pt" not in RunDir.MARKERS


def test_a_registered_method_runs_through_the_geometry_stage(tmp_path, toy):
    from vq_mitsuba.data.captures import load_mesh
    from vq_mitsuba.engine.pipeline import geometry_capture

    capture = _write_capture(tmp_path / "cap")
    result = geometry_capture(capture, tmp_path / "run", load_config(None, []), method="toy")
    run = RunDir(tmp_path / "run")
    assert result.method == "toy" and result.files == (run / TOY_STATE,) and not result.resumed
    assert run.geometry_summary() == {"views": 3, "background": "masks"}
    assert len(load_mesh(run / RunDir.MESH).faces) == len(result.mesh.faces) and not run.masks_from_mesh()
    assert methods.get(result.method).report(run.geometry_summary()) == ["Toy: a sphere for 3 views"]
    # its state is a run's file: the folder is a run, and a second stage resumes it
    (run / RunDir.GEOMETRY).unlink()
    (run / RunDir.MESH).unlink()
    assert run.holds_run_files() and TOY_STATE in RunDir.markers()
    again = geometry_capture(capture, run.dir, load_config(None, []), resume=True, method="toy")
    assert again.resumed


def test_a_method_without_masks_has_the_fit_mask_views_by_its_mesh(tmp_path, toy, monkeypatch):
    from vq_mitsuba.engine.pipeline import geometry_capture

    monkeypatch.setattr(type(toy), "masks_from_mesh", True)
    geometry_capture(_write_capture(tmp_path / "cap"), tmp_path / "run", load_config(None, []),
                     method="toy")
    run = RunDir(tmp_path / "run")
    assert run.geometry_summary()["background"] == "model" and run.masks_from_mesh()


def test_fit_reconstructs_with_the_method_it_names(tmp_path, toy, monkeypatch):
    import vq_mitsuba.engine.pipeline as pipeline

    seen, lines = [], []
    monkeypatch.setattr(pipeline, "fit_materials", lambda capture, *a, **k: seen.append(capture) or {"iterations": 1})
    capture = _write_capture(tmp_path / "cap")
    pipeline.fit_capture(capture, tmp_path / "run", load_config(None, []), geometry="toy",
                         log=lines.append)
    run = RunDir(tmp_path / "run")
    assert seen[0].mesh == run / RunDir.MESH and (run / TOY_STATE).is_file()
    assert lines == [f"geometry: reconstructed with Toy: {run / RunDir.MESH}", "Toy: a sphere for 3 views"]
    from vq_mitsuba.data.captures import open_capture
    from vq_mitsuba.errors import InputError

    assert pipeline.needs_reconstruction(open_capture(capture), "toy")
    with pytest.raises(InputError, match="--geometry toy asks to reconstruct it"):
        pipeline.needs_reconstruction(open_capture(capture, run / RunDir.MESH), "toy")


def test_the_cli_offers_the_registered_methods(tmp_path, toy, capsys):
    from vq_mitsuba import cli

    parser = cli.build_parser()
    fit = next(a for a in parser._subparsers._group_actions[0].choices["fit"]._actions if a.dest == "geometry")
    assert fit.choices == ["auto", "neus", "toy", "given"] and fit.default == "auto"


def test_an_unknown_method_is_refused_by_name_before_any_work(tmp_path, capsys):
    from vq_mitsuba import cli
    from vq_mitsuba.engine.pipeline import fit_capture, geometry_capture

    with pytest.raises(ValueError, match=r"unknown geometry method 'nope': the methods are neus"):
        methods.get("nope")
    capture = _write_capture(tmp_path / "cap")
    with pytest.raises(ValueError, match="unknown geometry method 'nope'"):
        geometry_capture(capture, tmp_path / "run", load_config(None, []), method="nope")
    with pytest.raises(ValueError, match=r"geometry must be one of \('auto', 'neus', 'given'\), got 'nope'"):
        fit_capture(capture, tmp_path / "run", load_config(None, []), geometry="nope")
    assert not (tmp_path / "run").exists()
    with pytest.raises(SystemExit) as info:
        cli.main(["fit", str(capture), "-o", str(tmp_path / "run"), "--geometry", "nope"])
    assert info.value.code == 2 and "invalid choice: 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("name", ["auto", "given"])
def test_a_method_may_not_take_a_mode_of_fit(name):
    with pytest.raises(ValueError, match="geometry mode of fit"):
        methods.register(name)(type("Clash", (Toy,), {}))
    assert name not in methods.names()
