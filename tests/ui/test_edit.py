"""Material edits: the operations themselves, and edits of a fitted run (the three-sphere capture)
that must change exactly the selected material, part or pixel's material, and nothing else."""

import json

import numpy as np
import pytest
import torch

from tiny_scene import THREE_MATERIALS, three_material_ids
from vq_mitsuba import cli
from vq_mitsuba.data.cameras import Camera
from vq_mitsuba.edit import build_edit, edit_run
from vq_mitsuba.run.run_dir import RunDir
from vq_mitsuba.errors import InputError
from vq_mitsuba.models.material_edits import (Change, Edit, Selection, apply_edits, check_change, hsv_to_rgb, hue_shift,
                                     material_library, rgb_to_hsv)
from vq_mitsuba.render.views import Renderer


# --- the operations -------------------------------------------------------------------------
def test_hsv_round_trip_and_hue_shift_keeps_saturation_and_value():
    rgb = torch.rand(500, 3, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(hsv_to_rgb(rgb_to_hsv(rgb)), rgb, atol=1e-5)
    shifted = hue_shift(rgb, 75.0)
    a, b = rgb_to_hsv(rgb), rgb_to_hsv(shifted)
    assert torch.allclose(a[:, 1:], b[:, 1:], atol=1e-5)
    dh = torch.remainder(b[:, 0] - a[:, 0], 1.0)
    coloured = a[:, 1] > 1e-3
    assert torch.allclose(dh[coloured], torch.full_like(dh[coloured], 75 / 360), atol=1e-4)
    assert torch.allclose(hue_shift(rgb, 360.0), rgb, atol=1e-5)
    red = torch.tensor([[0.8, 0.1, 0.1]])
    assert torch.allclose(hue_shift(red, 120.0), torch.tensor([[0.1, 0.8, 0.1]]), atol=1e-5)


def test_selection_is_material_and_box():
    pts = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    ids = torch.tensor([1, 1, 2, 2])
    box = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    assert Selection((1,), ()).mask(pts, ids).tolist() == [True, True, False, False]
    assert Selection((), (box,)).mask(pts, ids).tolist() == [True, False, True, False]
    assert Selection((1,), (box,)).mask(pts, ids).tolist() == [True, False, False, False]
    assert Selection((1, 2), (box,)).mask(pts, ids).tolist() == [True, False, True, False]


def test_edits_apply_in_order_and_relative_ones_keep_texture():
    n = 6
    brdf = {"basecolor": torch.linspace(0.1, 0.6, n)[:, None].repeat(1, 3) * torch.tensor([1.0, 0.5, 0.2]),
            "metallic": torch.full((n,), 0.2), "roughness": torch.linspace(0.2, 0.8, n)}
    pts = torch.zeros(n, 3)
    ids = torch.tensor([1, 1, 1, 2, 2, 2])
    edits = [Edit(Selection((1,)), [Change("scale", "roughness", 0.5)]),
             Edit(Selection((1,)), [Change("set", "metallic", 1.0), Change("set", "roughness", 0.9)]),
             Edit(Selection((2,)), [Change("scale", "roughness", 10.0)])]
    out = apply_edits(edits[:1], pts, brdf, ids, roughness_min=0.05)
    assert torch.allclose(out["roughness"][:3], brdf["roughness"][:3] * 0.5)  # detail kept, halved
    assert torch.equal(out["roughness"][3:], brdf["roughness"][3:]) and torch.equal(out["basecolor"], brdf["basecolor"])
    out = apply_edits(edits, pts, brdf, ids, roughness_min=0.05)
    assert torch.allclose(out["roughness"][:3], torch.full((3,), 0.9))  # the later edit wins
    assert out["metallic"][:3].eq(1.0).all() and out["metallic"][3:].eq(0.2).all()
    assert out["roughness"][3:].eq(1.0).all()  # clamped to the valid range


def test_bad_changes_and_edit_files_are_refused():
    with pytest.raises(ValueError, match="basecolor"):
        check_change(Change("set", "basecolor", (1.2, 0.0, 0.0)))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        check_change(Change("set", "roughness", 2.0))
    with pytest.raises(ValueError, match="finite"):
        check_change(Change("scale", "metallic", float("nan")))
    with pytest.raises(ValueError, match="unknown edit operation"):
        check_change(Change("blur", "metallic", 1.0))
    with pytest.raises(InputError, match="edit 1: .*material ids start at 1"):
        Edit.from_dict({"select": {"materials": [0]}, "changes": [{"op": "set", "key": "metallic", "value": 1}]})
    with pytest.raises(InputError, match="no changes"):
        Edit.from_dict({"select": {"materials": [1]}, "changes": []})


def test_library_materials_are_valid():
    lib = material_library()
    assert {"gold", "silver", "copper", "aluminium", "chrome", "red_plastic", "black_rubber", "ceramic"} <= set(lib)
    for name, m in lib.items():
        check_change(Change("set", "basecolor", tuple(m["basecolor"])))
        check_change(Change("set", "metallic", m["metallic"]))
        check_change(Change("set", "roughness", m["roughness"]))


# --- edits of a fitted run --------------------------------------------------------------------
def _ranked_id_of_sphere(fitted, k: int) -> int:
    """The ranked material id most points of sphere k (1..3) get from the discrete branch."""
    centre = np.array(THREE_MATERIALS[k - 1][0])
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    pts = centre + 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True)
    ids = fitted.materials_at(torch.as_tensor(pts, dtype=torch.float32))["material"]
    return int(torch.bincount(ids).argmax())


def _big(camera: Camera, size: int = 64) -> Camera:
    return Camera(camera.name, camera.to_world, camera.fov_x_deg, size, size)


def _srgb(x):
    from vq_mitsuba.data.imageio import linear_to_srgb

    return linear_to_srgb(np.clip(x, 0, 1))


def test_edit_material_changes_only_that_material(three_materials, tmp_path):
    """Direct light only: the changed pixels are K's. (With interreflections, neighbours that
    mirror K change too, as they should: the metal sphere beside K reflects it.)"""
    _, run = three_materials
    fitted = run.load()
    k = _ranked_id_of_sphere(fitted, 2)  # the glossy blue sphere
    out = edit_run(run, tmp_path / "gold", build_edit(run, fitted, materials=[k], preset="gold"))
    edited = out.load()
    fitted.cfg.train.bounces = edited.cfg.train.bounces = 0
    assert edited.edits and edited.edits[0].selection.materials == (k,)
    before, after = Renderer(fitted), Renderer(edited)
    inside_share = []
    for cam in run.cameras()["train"][:4]:
        cam = _big(cam)
        a = before.render(cam, spp=32, aa=4, seed=3)
        b = after.render(cam, spp=32, aa=4, seed=3)
        assert np.array_equal(a["material"], b["material"])  # the segmentation is the run's, unchanged
        changed = np.abs(_srgb(a["rgb"]) - _srgb(b["rgb"])).max(-1) > 2 / 255
        region = a["material"] == k
        # A pixel on K's border, counted under its majority material, may hold some of K's rays.
        grown = region | np.roll(region, 1, 0) | np.roll(region, -1, 0) | np.roll(region, 1, 1) | np.roll(region, -1, 1)
        assert changed.sum() > 0.5 * region.sum() > 0
        inside_share.append(float((changed & grown).sum() / changed.sum()))
        # Inside K (off its border) the maps are gold's.
        core = region & ~(grown & ~region | np.roll(~region, 1, 0) | np.roll(~region, -1, 0) | np.roll(~region, 1, 1)
                          | np.roll(~region, -1, 1))
        assert core.sum() > 0 and np.allclose(b["metallic"][core], 1.0, atol=1e-4)
    assert min(inside_share) >= 0.99, inside_share


def test_pick_selects_the_material_under_the_pixel(three_materials, tmp_path):
    capture, run = three_materials
    fitted = run.load()
    cam = run.cameras()["train"][0]
    checked = 0
    for k in (1, 2, 3):
        x, y = np.round(cam.project(np.array([THREE_MATERIALS[k - 1][0]]))[0] - 0.5).astype(int)
        # The sphere's centre projects onto sphere k unless another sphere hides it.
        from vq_mitsuba.data.cameras import camera_rays
        from vq_mitsuba.render.shading import scene_for_mesh

        o, d = camera_rays(cam)
        i = y * cam.width + x
        hit = scene_for_mesh(fitted.mesh, fitted.envmap, fitted.envmap_to_world).trace(o[i:i + 1], d[i:i + 1])
        if int(three_material_ids(hit.position.numpy())[0]) != k:
            continue
        edit = build_edit(run, fitted, picks=[f"{cam.name}:{x},{y}"], sets=["roughness=0.5"])
        assert edit.selection.materials == (_ranked_id_of_sphere(fitted, k),)
        checked += 1
    assert checked >= 2
    with pytest.raises(InputError, match="background"):
        build_edit(run, fitted, picks=[f"{cam.name}:0,0"], sets=["roughness=0.5"])
    with pytest.raises(InputError, match="no view named 'nope'"):
        build_edit(run, fitted, picks=["nope:3,3"], sets=["roughness=0.5"])


def test_box_edits_one_part_of_a_material(three_materials, tmp_path):
    """The red sphere's upper half (a part sharing its material with the lower half) turns blue;
    its lower half and the other spheres keep their BRDF."""
    _, run = three_materials
    fitted = run.load()
    k = _ranked_id_of_sphere(fitted, 1)
    # The box also holds the top of the gold sphere, which the material selection keeps out.
    box = "-1,0.05,-1,1,1,1"
    out = edit_run(run, tmp_path / "box", build_edit(run, fitted, materials=[k], boxes=[box],
                                                     sets=["basecolor=0.1,0.2,0.9"]))
    edited = out.load()
    rng = np.random.default_rng(1)
    for sphere in (1, 2, 3):
        d = rng.normal(size=(300, 3))
        pts = torch.as_tensor(np.array(THREE_MATERIALS[sphere - 1][0]) + 0.3 * d / np.linalg.norm(d, axis=1)[:, None],
                              dtype=torch.float32)
        a, b = fitted.materials_at(pts), edited.materials_at(pts)
        moved = (a["basecolor"] - b["basecolor"]).abs().max(-1).values > 1e-6
        upper = pts[:, 1] >= 0.05
        on_k = a["material"] == k
        assert torch.equal(moved, upper & on_k)
        if sphere == 1:
            assert moved.float().mean() > 0.3 and torch.allclose(b["basecolor"][moved], torch.tensor([0.1, 0.2, 0.9]))


def test_edit_list_is_replayable_and_undoable(three_materials, tmp_path):
    _, run = three_materials
    fitted = run.load()
    first = edit_run(run, tmp_path / "e1", build_edit(run, fitted, materials=[1], hue_shift=90.0))
    second = edit_run(first, tmp_path / "e2", build_edit(run, fitted, materials=[2], scales=["roughness=0.5"]))
    info = second.info()
    assert info["edit_of"]["absolute"] == str(run.dir.resolve())  # an edit of an edit refers to the fit
    assert [e.selection.materials for e in second.edits()] == [(1,), (2,)]
    pts = torch.as_tensor(np.random.default_rng(2).uniform(-0.9, 0.9, (2000, 3)), dtype=torch.float32)
    both, one = second.load().materials_at(pts), first.load().materials_at(pts)
    # Undo: drop the second entry of edits.json by hand; the run is then the first edit again.
    data = json.loads((second / RunDir.EDITS).read_text())
    data["edits"] = data["edits"][:1]
    (second / RunDir.EDITS).write_text(json.dumps(data))
    undone = second.load().materials_at(pts)
    for key in ("basecolor", "metallic", "roughness"):
        assert torch.equal(undone[key], one[key])
    assert not torch.equal(both["roughness"], one["roughness"])
    data["edits"] = []
    (second / RunDir.EDITS).write_text(json.dumps(data))
    assert torch.equal(second.load().materials_at(pts)["basecolor"], fitted.materials_at(pts)["basecolor"])


def test_edit_command_line(three_materials, tmp_path, capsys):
    _, run = three_materials
    out = tmp_path / "cli_edit"
    assert cli.main(["edit", str(run.dir), "--material", "1", "--set", "basecolor=#ff0000", "--scale",
                     "roughness=0.5", "-o", str(out)]) == 0
    edits = json.loads((out / "edits.json").read_text())["edits"]
    assert edits[0]["label"] == "--material 1 --set basecolor=#ff0000 --scale roughness=0.5"
    assert edits[0]["changes"][0]["value"] == [1.0, 0.0, 0.0]  # sRGB #ff0000 is linear (1, 0, 0)
    # Bad input: one message, exit 2, nothing written.
    for argv, message in [
        (["--set", "roughness=0.5"], "select what to edit"),
        (["--material", "1"], "no change given"),
        (["--material", "9", "--set", "roughness=0.5"], "materials 1..3"),
        (["--material", "1", "--preset", "unobtainium"], "unknown material preset"),
        (["--material", "1", "--set", "roughness=1.5"], "must lie in [0, 1]"),
        (["--box", "0,0,0,1,1", "--set", "roughness=0.5"], "expected 6 numbers"),
    ]:
        target = tmp_path / "bad"
        assert cli.main(["edit", str(run.dir), *argv, "-o", str(target)]) == 2
        assert message in capsys.readouterr().err
        assert not target.exists()
    assert cli.main(["edit", str(run.dir), "--material", "1", "--set", "metallic=1", "-o", str(run.dir)]) == 2
    assert "holds a fitted run" in capsys.readouterr().err


def test_box_with_negative_corners_on_the_command_line(three_materials, tmp_path):
    _, run = three_materials
    out = tmp_path / "neg_box"
    assert cli.main(["edit", str(run.dir), "--box", "-2,-2,-2,2,0,2", "--set", "roughness=0.5", "-o", str(out)]) == 0
    box = json.loads((out / "edits.json").read_text())["edits"][0]["select"]["boxes"][0]
    assert box == [[-2.0, -2.0, -2.0], [2.0, 0.0, 2.0]]
