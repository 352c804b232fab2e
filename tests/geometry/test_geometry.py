"""Geometry from images: NeuS, marching cubes, mesh clean-up, metrics, and the CLI's handling."""

from __future__ import annotations

import dataclasses
from dataclasses import replace
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import trimesh

from vq_mitsuba.data.cameras import Camera, look_at
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.errors import InputError
from vq_mitsuba.config import NeuSConfig, load_config
from vq_mitsuba.geometry.neus import grid_kernel
from vq_mitsuba.geometry.mesh import clean_mesh, component_sizes, marching_cubes, mesh_metrics, smooth_vertex_normals
from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.geometry.neus.networks import COARSE_TO_FINE, COARSE_TO_FINE_FINE
from vq_mitsuba.geometry.neus import (COARSE_GRID, FINE_GRID, HASH_PRIMES, MASKED_GRID, ColorNetwork, DenseGrid,
                                      NeuSModel, hull_box, choose_grid, rate_spread, reconstruct, train)
from vq_mitsuba.geometry.neus import NeuS, neus_for

RADIUS = 0.5


def sphere_capture(n_views: int = 12, size: int = 32, with_alpha: bool = True) -> Capture:
    """Analytic captures of a diffuse sphere (radius 0.5 at the origin) lit from one direction."""
    cams = []
    golden = np.pi * (3 - np.sqrt(5))
    for i in range(n_views):
        z = 0.8 - 1.4 * (i + 0.5) / n_views
        r = np.sqrt(1 - z * z)
        d = np.array([r * np.cos(golden * i), r * np.sin(golden * i), z])
        cams.append(Camera(f"v{i}", look_at(2.5 * d, [0, 0, 0], [0, 0, 1]), 40.0, size, size))
    light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    images, alphas = [], []
    for cam in cams:
        o, d = camera_rays(cam)
        b = np.sum(o * d, 1)
        c = np.sum(o * o, 1) - RADIUS ** 2
        disc = b * b - c
        hit = disc > 0
        t = -b - np.sqrt(np.maximum(disc, 0))
        n = (o + t[:, None] * d) / RADIUS
        shade = 0.1 + 0.7 * np.clip(n @ light, 0, None)
        rgb = np.where(hit[:, None], shade[:, None] * np.array([0.9, 0.6, 0.3]), 0.0)
        images.append(rgb.reshape(size, size, 3))
        alphas.append(hit.reshape(size, size).astype(np.float32))
    images = np.stack(images).astype(np.float32)
    alpha = np.stack(alphas) if with_alpha else np.ones(images.shape[:3], np.float32)
    return Capture(Path("analytic_sphere.json"), cams, images, alpha, with_alpha, None, None, np.eye(4), "blender")


def small_cfg(**kw) -> NeuSConfig:
    base = dict(batch_rays=256, n_samples=16, levels=3, base_res=8, max_res=24, hidden=32, hull_resolution=48,
                march_steps=64, mesh_resolution=48, checkpoint_every=0, warmup=10, threads=1)
    base.update(kw)
    return load_config(None, [f"neus.{k}={v}" for k, v in base.items()]).neus


def sdf_world(neus: NeuS, points: np.ndarray) -> np.ndarray:
    """The NeuS SDF at world points, in world units."""
    p = neus.to_box(torch.tensor(points, device=neus.device))
    with torch.no_grad():
        s = neus.model.sdf(p, [1.0] * neus.cfg.levels)[0]
    return s.cpu().numpy() * neus.box.half


def test_dense_grid_is_trilinear_and_twice_differentiable():
    torch.manual_seed(0)
    grid = DenseGrid(2, 4, 8, 1)
    # Fill every level with the linear function a.x + b (trilinear interpolation reproduces it exactly).
    a = torch.tensor([0.3, -0.7, 0.2])
    with torch.no_grad():
        start = 0
        for r in grid.res:
            c = (torch.arange(r) + 0.5) / r * 2 - 1
            pts = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
            grid.table[start:start + r ** 3, 0] = pts @ a + 0.1
            start += r ** 3
    p = (torch.rand(200, 3) * 1.4 - 0.7).requires_grad_(True)
    out = grid(p, [1.0, 1.0])
    expected = (p @ a + 0.1).detach()
    assert torch.allclose(out[:, 0], expected, atol=1e-5)
    assert torch.allclose(out[:, 1], expected, atol=1e-5)
    g = torch.autograd.grad(out.sum(), p, create_graph=True)[0]
    assert torch.allclose(g, (2 * a).expand_as(g), atol=1e-4)
    # The eikonal-style loss on the gradient reaches the grid values (double backward).
    ((g.norm(dim=-1) - 1) ** 2).mean().backward()
    assert grid.table.grad is not None and grid.table.grad.abs().sum() > 0
    # A disabled level contributes nothing.
    assert torch.all(grid(p.detach(), [1.0, 0.0])[:, 1] == 0)


def test_hashed_levels_look_up_their_spatial_hash_and_are_twice_differentiable():
    torch.manual_seed(0)
    dense = DenseGrid(2, 4, 16, 1)
    hashed = DenseGrid(2, 4, 16, 1, hash_log2=9)  # 16^3 points > 2^9: the fine level is hashed
    assert dense.table.shape[0] == 4 ** 3 + 16 ** 3 and hashed.table.shape[0] == 4 ** 3 + 2 ** 9
    assert DenseGrid(2, 4, 16, 1, hash_log2=12).table.shape[0] == dense.table.shape[0]  # 2^12 holds 16^3
    with torch.no_grad():
        hashed.table.normal_()
    # At a fine level's grid point, the lookup is the table row its coordinates hash to.
    ijk = torch.tensor([[3, 7, 12], [0, 0, 0], [15, 2, 9], [14, 14, 14]])
    p = (ijk.float() + 0.5) / 16 * 2 - 1
    out = hashed(p, [0.0, 1.0])[:, 1]
    rows = (ijk[:, 0] * HASH_PRIMES[0]) ^ (ijk[:, 1] * HASH_PRIMES[1]) ^ (ijk[:, 2] * HASH_PRIMES[2])
    assert torch.allclose(out, hashed.table[4 ** 3 + (rows & (2 ** 9 - 1)), 0], atol=1e-6)
    # Between grid points it stays continuous, and the eikonal-style loss reaches hashed rows.
    q = (torch.rand(300, 3) * 1.4 - 0.7).requires_grad_(True)
    eps = 1e-3
    step = torch.tensor([eps, 0.0, 0.0])
    fd = (hashed(q.detach() + step, [1.0, 1.0]).sum(1) - hashed(q.detach() - step, [1.0, 1.0]).sum(1)) / (2 * eps)
    g = torch.autograd.grad(hashed(q, [1.0, 1.0]).sum(), q, create_graph=True)[0]
    # away from either level's cell faces along x, where the derivative jumps
    inside = torch.stack([((q.detach()[:, 0] + 1) * (r / 2) - 0.5).frac().sub(0.5).abs() < 0.49 for r in (4, 16)]).all(0)
    assert torch.allclose(g[inside, 0], fd[inside], rtol=1e-2, atol=1e-2)
    ((g.norm(dim=-1) - 1) ** 2).mean().backward()
    assert hashed.table.grad[4 ** 3:].abs().sum() > 0


@pytest.mark.parametrize("hull,layers", [(True, 2), (False, 2), (True, 1)])
def test_the_closed_form_sdf_gradient_matches_autograd_and_so_do_its_parameter_gradients(hull, layers):
    """NeuS trains on the SDF gradient computed in closed form; it and every parameter gradient of a
    loss on it (eikonal, normals into the colour) equal autograd's double backward through the plain
    forward, with hashed and dense levels, the hull's base grid or a sphere, points the grid clamps,
    and one or two hidden layers."""
    torch.manual_seed(1)
    cfg = small_cfg(levels=3, base_res=4, max_res=32, hash_log2=12, hidden=16, geo_features=5, sdf_layers=layers)
    base = torch.randn(16 ** 3) * 0.1 if hull else None
    model = NeuSModel(cfg, base).double()
    assert model.sdf.encoding.hashed == [False, False, True]
    with torch.no_grad():
        model.sdf.encoding.table.normal_(0.0, 0.3)
        model.sdf.out.weight.normal_(0.0, 0.3)
    p = torch.rand(400, 3, dtype=torch.float64) * 2.2 - 1.1  # some beyond the grid's outer cell centres
    view = F.normalize(torch.randn(400, 3, dtype=torch.float64), dim=-1)
    lw = [1.0, 0.7, 0.3]

    def loss_of(sdf, feat, grad):
        normal = F.normalize(grad, dim=-1)
        colour = model.color(feat, normal, view)
        return ((grad.norm(dim=-1) - 1.0) ** 2).mean() + colour.square().mean() + (sdf * view[:, 0]).mean()

    params = [q for q in model.parameters() if q.requires_grad]
    sdf, feat, grad = model.sdf_grad(p, lw, create_graph=True)
    closed = torch.autograd.grad(loss_of(sdf, feat, grad), params, allow_unused=True)
    q = p.clone().requires_grad_(True)
    sdf_ref, feat_ref = model.sdf(q, lw)
    grad_ref = torch.autograd.grad(sdf_ref.sum(), q, create_graph=True)[0]
    reference = torch.autograd.grad(loss_of(sdf_ref, feat_ref, grad_ref), params, allow_unused=True)
    assert torch.allclose(sdf, sdf_ref, atol=1e-12) and torch.allclose(feat, feat_ref, atol=1e-12)
    assert torch.allclose(grad, grad_ref, rtol=1e-9, atol=1e-9)
    assert grad.abs().max() > 0.5  # the grid and the MLP do shape it
    for a, b in zip(closed, reference):
        assert (a is None) == (b is None)
        if a is not None:
            # softplus is the identity past its threshold, where its derivative sigmoid(20) is 1 - 2e-9
            assert torch.allclose(a, b, rtol=1e-8, atol=1e-9)
    assert sum(float(a.abs().sum()) for a in closed if a is not None) > 0
    # Without create_graph the gradient is data, not part of the graph.
    assert not model.sdf_grad(p, lw, create_graph=False)[2].requires_grad


needs_kernel = pytest.mark.skipif(grid_kernel.status() != "compiled kernel", reason=grid_kernel.status())


@needs_kernel
@pytest.mark.parametrize("jacobian", [False, True])
def test_the_compiled_grid_lookup_matches_the_torch_lookup_and_its_table_gradient(jacobian):
    """The CPU kernel against `DenseGrid.forward_torch`: features, their Jacobian and the table's
    gradient of a random linear loss on both, with dense and hashed levels, a level faded out and
    points the grid clamps or that lie far outside it."""
    torch.manual_seed(2)
    grid = DenseGrid(4, 4, 40, 3, hash_log2=12)
    assert grid.hashed == [False, False, True, True]
    with torch.no_grad():
        grid.table.normal_()
    p = torch.rand(3000, 3) * 2.6 - 1.3
    p[:10] = torch.tensor([1e6, -1e6, 0.0])
    lw = [1.0, 0.6, 0.25, 0.0]
    out = grid(p, lw, jacobian=jacobian)
    ref = grid.forward_torch(p, lw, jacobian=jacobian)
    out, ref = (out, ref) if jacobian else ((out,), (ref,))
    weights = [torch.randn_like(r) for r in ref]
    grads = []
    for values in (out, ref):
        assert values[0].grad_fn is not None
        grid.table.grad = None
        sum((v * w).sum() for v, w in zip(values, weights)).backward()
        grads.append(grid.table.grad.clone())
    for a, b in zip(out, ref):
        assert a.shape == b.shape and torch.allclose(a, b, rtol=1e-5, atol=1e-5)
    assert torch.allclose(grads[0], grads[1], rtol=1e-4, atol=1e-4)
    assert grads[0].abs().max() > 1 and torch.all(out[0][:, 9:] == 0)  # the faded-out level: no feature
    with torch.no_grad():
        nan = grid(torch.tensor([[float("nan"), 0.0, 0.0], [0.2, 0.1, -0.3]]), lw, jacobian=True)
    assert torch.isnan(nan[0][0]).any() and torch.isfinite(nan[0][1]).all()  # bad input stays in its row


@needs_kernel
def test_the_sdf_network_on_the_kernel_matches_it_on_torch_with_every_parameter_gradient(monkeypatch):
    """A NeuS step's quantities (SDF, features, closed-form gradient, the hull's base grid) and the
    parameter gradients of a loss on them are the same whichever lookup runs."""
    torch.manual_seed(3)
    cfg = small_cfg(levels=3, base_res=4, max_res=32, hash_log2=12, hidden=16, geo_features=5)
    model = NeuSModel(cfg, torch.randn(16 ** 3) * 0.1)
    with torch.no_grad():
        model.sdf.encoding.table.normal_(0.0, 0.3)
    p = torch.rand(500, 3) * 2.2 - 1.1
    view = F.normalize(torch.randn(500, 3), dim=-1)
    params = [q for q in model.parameters() if q.requires_grad]

    def run():
        sdf, feat, grad = model.sdf_grad(p, [1.0, 0.7, 0.3], create_graph=True)
        loss = (((grad.norm(dim=-1) - 1.0) ** 2).mean() + model.color(feat, F.normalize(grad, dim=-1), view).mean()
                + sdf.mean())
        return [sdf, feat, grad], torch.autograd.grad(loss, params, allow_unused=True)

    kernel_values, kernel_grads = run()
    monkeypatch.setattr(grid_kernel, "usable", lambda *args: False)
    torch_values, torch_grads = run()
    for a, b in zip(kernel_values + list(kernel_grads), torch_values + list(torch_grads)):
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)


def test_the_grid_is_finer_when_the_object_spans_more_pixels():
    """The auto grid with masks: 5 levels to 128 for a small image of the object, the fine grid
    when the working box spans hundreds of pixels; without masks the coarse grid; given values are
    kept."""
    center, half = np.zeros(3), 0.8
    small = sphere_capture(n_views=6, size=64).cameras
    large = [c.scaled(1024, 1024) for c in small]
    auto = NeuSConfig()
    (cfg_small, grid_small), (cfg_large, grid_large) = (choose_grid(auto, cams, center, half) for cams in (small, large))
    assert (cfg_small.levels, cfg_small.max_res) == MASKED_GRID and grid_small["box_footprint_px"] < 256
    assert (cfg_large.levels, cfg_large.max_res) == FINE_GRID and grid_large["box_footprint_px"] > 256
    assert "over 256" in grid_large["reason"] and "at most 256" in grid_small["reason"]
    # the fine grid's photos are seen about once: one hidden SDF layer there, two elsewhere
    assert (cfg_large.sdf_layers, grid_large["sdf_layers"], cfg_small.sdf_layers) == (1, 1, 2)
    assert choose_grid(replace(auto, sdf_layers=2), large, center, half)[0].sdf_layers == 2
    # ... and every grid level from the first step there, the finer levels fading in elsewhere
    assert (cfg_large.coarse_to_fine, grid_large["coarse_to_fine"], cfg_small.coarse_to_fine) == (
        COARSE_TO_FINE_FINE, 0.0, COARSE_TO_FINE) and COARSE_TO_FINE > 0
    assert choose_grid(replace(auto, coarse_to_fine=0.5), large, center, half)[0].coarse_to_fine == 0.5
    # without masks the background model shares the steps: the coarse grid whatever the size
    cfg_free, grid_free = choose_grid(auto, large, center, half, masks=False)
    assert (cfg_free.levels, cfg_free.max_res) == COARSE_GRID and "without masks" in grid_free["reason"]
    assert cfg_free.sdf_layers == 2
    given, info = choose_grid(replace(auto, levels=3, max_res=24), large, center, half)
    assert (given.levels, given.max_res) == (3, 24) and info["reason"] == "neus.levels and neus.max_res given"
    # the coarse grid is dense, the finer ones hash their finest levels
    assert not any(DenseGrid(COARSE_GRID[0], 16, COARSE_GRID[1], 2, auto.hash_log2).hashed)
    assert DenseGrid(MASKED_GRID[0], 16, MASKED_GRID[1], 2, auto.hash_log2).hashed == [False] * 4 + [True]
    assert any(DenseGrid(FINE_GRID[0], 16, FINE_GRID[1], 2, auto.hash_log2).hashed)


def test_the_hull_keeps_an_object_wider_than_most_frames():
    """A bar longer than most views' frames (as a real object that fills close-up photos): its
    ends, seen by a minority of the views and never as background, stay in the visual hull."""
    half = np.array([1.5, 0.2, 0.2])
    cams = []
    golden = np.pi * (3 - np.sqrt(5))
    for i in range(30):
        z = 0.9 - 1.8 * (i + 0.5) / 30
        r = np.sqrt(1 - z * z)
        d = np.array([z, r * np.cos(golden * i), r * np.sin(golden * i)])
        cams.append(Camera(f"v{i}", look_at(3.0 * d, [0, 0, 0], [0, 0, 1] if abs(d[2]) < 0.9 else [0, 1, 0]),
                           40.0, 48, 48))
    masks = []
    for cam in cams:
        o, d = camera_rays(cam)
        inv = 1.0 / np.where(np.abs(d) < 1e-9, 1e-9, d)
        t1, t2 = (-half - o) * inv, (half - o) * inv
        hit = np.minimum(t1, t2).max(1) < np.maximum(t1, t2).min(1)
        masks.append(hit.reshape(48, 48))
    masks = torch.from_numpy(np.stack(masks))
    ends = np.array([[1.35, 0.0, 0.0], [-1.35, 0.0, 0.0]])
    framed = np.mean([[0 <= x < 48 and 0 <= y < 48 for x, y in cam.project(ends)] for cam in cams], 0)
    assert np.all(framed < 0.75)  # the ends are in the frame of fewer than 3 views in 4

    def kept(min_views: float) -> bool:
        c, h, occ = hull_box(cams, masks, NeuSConfig(hull_resolution=48, hull_min_views=min_views), "bar")
        idx = np.floor(((ends - c) / h + 1) / 2 * occ.shape[0]).astype(int)
        inside = np.all((idx >= 0) & (idx < occ.shape[0]), 1)
        return bool(inside.all() and occ.numpy()[idx[:, 0], idx[:, 1], idx[:, 2]].all())

    assert kept(NeuSConfig().hull_min_views)
    assert not kept(0.75)


def test_marching_cubes_on_analytic_sphere_gives_radius():
    n, r = 48, 0.6
    ax = np.linspace(-1, 1, n)
    x, y, z = np.meshgrid(ax, ax, ax, indexing="ij")
    vol = np.sqrt(x ** 2 + y ** 2 + (z - 0.1) ** 2) - r
    mesh = marching_cubes(vol, (-1, -1, -1), (1, 1, 1))
    radii = np.linalg.norm(mesh.vertices - [0, 0, 0.1], axis=1)
    assert abs(radii.mean() - r) < 0.01 and radii.std() < 0.01
    assert mesh.volume > 0  # outward normals
    assert abs(mesh.volume - 4 / 3 * np.pi * r ** 3) < 0.03 * 4 / 3 * np.pi * r ** 3
    with pytest.raises(ValueError):
        marching_cubes(np.ones((4, 4, 4)), (-1, -1, -1), (1, 1, 1))


def test_clean_mesh_removes_small_floating_piece_but_keeps_other_objects():
    big = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    twin = trimesh.creation.icosphere(subdivisions=3, radius=0.45)
    twin.apply_translation([2.0, 0, 0])
    speck = trimesh.creation.icosphere(subdivisions=0, radius=0.02)
    speck.apply_translation([0, 1.5, 0])
    mesh = trimesh.util.concatenate([big, twin, speck])
    assert len(component_sizes(mesh)) == 3
    cleaned = clean_mesh(mesh, min_component=0.05)
    sizes = sorted(component_sizes(cleaned))
    assert sizes == [len(big.faces), len(twin.faces)]  # the speck is gone, both objects stay
    assert np.linalg.norm(cleaned.vertices, axis=1).max() < 2.5
    largest = clean_mesh(mesh, keep_largest=True)
    assert len(component_sizes(largest)) == 1 and len(largest.faces) == len(big.faces)
    decimated = clean_mesh(big, max_faces=300)
    assert len(decimated.faces) <= 300 and decimated.volume > 0


def test_normal_smoothing_removes_bumps_keeps_positions_and_survives_ply(tmp_path):
    from vq_mitsuba.data.captures import load_mesh

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    v = sphere.vertices.copy()
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    # Ripples a few edges wide, 0.2 % of the radius high: the normals tilt by a degree or more.
    bumpy = v + 0.001 * np.sin(60 * v[:, :1]) * np.cos(60 * v[:, 1:2]) * d
    mesh = trimesh.Trimesh(bumpy, sphere.faces, process=False)

    def err_deg(normals):
        return np.degrees(np.arccos(np.clip(np.sum(normals * d, axis=1), -1, 1)))

    before = err_deg(mesh.vertex_normals)
    smoothed = smooth_vertex_normals(mesh, 20)
    after = err_deg(smoothed.vertex_normals)
    assert np.median(before) > 1.0
    assert np.median(after) < np.median(before) / 3
    assert np.array_equal(smoothed.vertices, mesh.vertices) and np.array_equal(smoothed.faces, mesh.faces)
    assert np.allclose(np.linalg.norm(smoothed.vertex_normals, axis=1), 1.0, atol=1e-6)
    assert np.allclose(smooth_vertex_normals(mesh, 0).vertex_normals, mesh.vertex_normals)
    # The material stage reads mesh.ply with load_mesh: the smoothed normals must come back.
    smoothed.export(tmp_path / "mesh.ply")
    back = load_mesh(tmp_path / "mesh.ply")
    assert np.allclose(back.vertex_normals, smoothed.vertex_normals, atol=1e-6)


def test_normal_smoothing_within_an_angle_keeps_creases():
    # A box whose faces are fine grids (vertices shared along the edges, as marching cubes makes
    # them) with bumpy normals: averaging within 15 degrees flattens the faces but does not bend
    # the normals next to an edge towards the other face, as plain averaging does.
    box = trimesh.creation.box((1.0, 1.0, 1.0)).subdivide().subdivide().subdivide().subdivide()
    box.merge_vertices()
    rng = np.random.default_rng(0)
    v = np.asarray(box.vertices)
    true_n = np.zeros_like(v)
    axis = np.argmax(np.abs(v), axis=1)  # the face a vertex belongs to (off the edges)
    true_n[np.arange(len(v)), axis] = np.sign(v[np.arange(len(v)), axis])
    off_edge = np.sort(np.abs(v), axis=1)[:, 1] < 0.5 - 0.1  # at least 3 edges of the grid from a crease
    bumpy = np.asarray(box.vertex_normals) + 0.08 * rng.standard_normal(v.shape)
    bumpy /= np.linalg.norm(bumpy, axis=1, keepdims=True)
    mesh = trimesh.Trimesh(v, box.faces, vertex_normals=bumpy, process=False)

    def err_deg(m):
        return np.degrees(np.arccos(np.clip(np.sum(np.asarray(m.vertex_normals)[off_edge] * true_n[off_edge], 1), -1, 1)))

    plain = err_deg(smooth_vertex_normals(mesh, 40))
    crease = err_deg(smooth_vertex_normals(mesh, 40, max_angle_deg=15.0))
    assert np.median(err_deg(mesh)) > 3.0
    assert np.median(crease) < 1.0
    assert np.percentile(crease, 90) < 0.5 * np.percentile(plain, 90)


def test_mesh_metrics_measure_distance_and_normals():
    a = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    same = mesh_metrics(a, a, n_points=20000)
    assert same["chamfer_rel"] < 0.005 and same["normal_consistency"] > 0.98
    b = trimesh.creation.icosphere(subdivisions=4, radius=0.55)
    off = mesh_metrics(b, a, n_points=20000)
    diag = np.linalg.norm(np.ptp(a.vertices, axis=0))
    assert abs(off["chamfer"] - 0.05) < 0.01
    assert abs(off["chamfer_rel"] - 0.05 / diag) < 0.01 / diag
    box = trimesh.creation.box((1, 1, 1))
    assert mesh_metrics(box, a, n_points=20000)["normal_consistency"] < same["normal_consistency"] - 0.05
    # Shading normals: small on the same mesh; a tilt of the stored vertex normals by 10 degrees
    # shows in them (and not in the face-normal consistency).
    assert same["shading_normal_deg_median"] < 1.0
    axis = np.cross(a.vertex_normals, [0.0, 0.0, 1.0])
    axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-9)
    t = np.radians(10.0)
    tilted = a.vertex_normals * np.cos(t) + np.cross(axis, a.vertex_normals) * np.sin(t)
    shaded = mesh_metrics(trimesh.Trimesh(a.vertices, a.faces, vertex_normals=tilted, process=False), a, n_points=20000)
    assert 8.0 < shaded["shading_normal_deg_median"] < 11.0
    assert shaded["normal_consistency"] == pytest.approx(same["normal_consistency"], abs=1e-6)


def test_neus_moves_a_wrong_sphere_to_the_true_surface():
    capture = sphere_capture()
    cfg = small_cfg(init="sphere", init_radius=0.5, iterations=150, seed=1)
    neus = neus_for(capture, cfg)
    d = np.random.default_rng(0).normal(size=(500, 3))
    on_surface = RADIUS * d / np.linalg.norm(d, axis=1, keepdims=True)
    before = np.abs(sdf_world(neus, on_surface)).mean()
    train(neus, None)
    after = np.abs(sdf_world(neus, on_surface)).mean()
    assert before > 0.05
    assert after < 0.02 and after < before / 3
    # Inside negative, outside positive.
    assert sdf_world(neus, np.zeros((1, 3)))[0] < 0
    assert sdf_world(neus, np.array([[0.0, 0.0, 0.8]]))[0] > 0


def test_reconstruct_smoke_makes_a_mesh_and_resumes(tmp_path):
    capture = sphere_capture(n_views=8, size=24)
    result = reconstruct(capture, tmp_path, small_cfg(iterations=4, checkpoint_every=2))
    info = result.summary
    assert len(result.mesh.faces) == info["mesh"]["faces"] and result.neus.cfg.iterations == 4
    for name in ("geometry_loss.png", "neus.pt"):
        assert (tmp_path / name).is_file(), name
    # mesh.ply and geometry.json are the geometry stage's (geometry/stage.py), not the model's.
    assert not (tmp_path / "mesh.ply").exists() and not (tmp_path / "geometry.json").exists()
    mesh = result.mesh
    radii = np.linalg.norm(mesh.vertices, axis=1)
    # 4 steps from the visual hull of 8 low-resolution views: a closed blob around the true sphere.
    assert 0.45 < np.median(radii) < 0.65 and mesh.is_watertight
    assert info["iterations"] == 4
    assert info["seconds"]["train"] > 0
    again = reconstruct(capture, tmp_path, small_cfg(iterations=6), resume=True)
    assert again.summary["iterations"] == 6
    # Resuming under other network shapes is refused by name, and the checkpoint is kept.
    other = not small_cfg().reflect
    with pytest.raises(InputError, match=f"neus.reflect={not other} \\(now {other}\\)") as err:
        reconstruct(capture, tmp_path, small_cfg(iterations=8, reflect=other), resume=True)
    assert err.value.path == tmp_path / "neus.pt"
    assert torch.load(tmp_path / "neus.pt", weights_only=False)["step"] == 6


def test_neus_scores_its_own_renders_inside_the_masks_and_training_raises_them():
    from vq_mitsuba.geometry.neus.training import sample_views, view_psnr
    from vq_mitsuba.geometry.neus.method import neus_psnr_line

    capture = sphere_capture(n_views=8, size=24)
    neus = neus_for(capture, small_cfg(iterations=80))
    views = sample_views(len(capture.cameras), 3)
    assert views == [0, 4, 7] and sample_views(2, 4) == [0, 1] and sample_views(0, 4) == []
    neus.refresh_occupancy(neus.level_weights(1.0))
    before = view_psnr(neus, capture, views)
    train(neus, None)
    after = view_psnr(neus, capture, views)
    assert set(after) == {capture.cameras[v].name for v in views}
    assert np.mean(list(after.values())) > np.mean(list(before.values())) + 5.0
    # Only the pixels inside the masks count: the backdrop may be anything.
    painted = replace(capture, images=np.where(capture.alpha[..., None] > 0.5, capture.images, 1.0).astype(np.float32))
    assert view_psnr(neus, painted, views) == pytest.approx(after, abs=1e-4)
    line = neus_psnr_line({"train_views": 21.5, "holdout_views": 19.25, "inside_masks": True})
    assert line == "NeuS renders its training views at 21.50 dB inside the masks, its held-out views at 19.25 dB"


def test_neus_trains_for_its_time_budget_without_a_step_limit_unless_told():
    from vq_mitsuba.geometry.neus.renderer import choose_iterations

    timed = NeuSConfig(batch_rays=512)
    assert timed.iterations == 0 and timed.time_limit_s > 0
    cfg, info = choose_iterations(timed, 3_443_727)
    assert cfg.iterations == info["iterations"] == 0 and "no step limit" in info["reason"]
    # Without a time limit: two passes over the training rays, within 4000-11000 steps.
    auto = NeuSConfig(batch_rays=512, time_limit_s=0)
    for rays, steps in ((100_000, 4000), (1_280_000, 5000), (2_560_000, 10000), (3_443_727, 11000)):
        cfg, info = choose_iterations(auto, rays)
        assert cfg.iterations == info["iterations"] == steps and info["training_rays"] == rays
    cfg, info = choose_iterations(replace(auto, iterations=123), 3_443_727)
    assert cfg.iterations == 123 and info["reason"] == "neus.iterations given"
    neus = neus_for(sphere_capture(n_views=6, size=16), small_cfg(iterations=0, batch_rays=64, time_limit_s=0))
    assert neus.cfg.iterations == neus.steps["iterations"] == 4000 and neus.steps["training_rays"] == len(neus.rays_o)


def test_neus_needs_masks_and_foreground():
    with pytest.raises(InputError, match="alpha"):  # without masks only when neus.background allows it
        neus_for(sphere_capture(n_views=4, size=16, with_alpha=False), small_cfg(background="masks"))
    empty = sphere_capture(n_views=4, size=16)
    empty.alpha[:] = 0.0
    with pytest.raises(InputError, match="empty"):
        neus_for(empty, small_cfg())


def test_config_overrides_are_checked():
    cfg = load_config(None, ["neus.iterations=12", "neus.keep_largest=true", "neus.lr=0.5"]).neus
    assert cfg.iterations == 12 and cfg.keep_largest is True and cfg.lr == 0.5
    with pytest.raises(InputError, match="unknown config key 'neus.nope'"):
        load_config(None, ["neus.nope=1"])
    with pytest.raises(InputError, match="'neus.iterations' expects int"):
        load_config(None, ["neus.iterations=many"])
    with pytest.raises(InputError, match="normal_smoothing"):
        load_config(None, ["neus.normal_smoothing=-1"])


def _write_json_capture(folder: Path, with_alpha: bool, n_frames: int = 2) -> Path:
    import imageio.v3 as iio

    (folder / "images").mkdir(parents=True)
    frames = []
    for i in range(n_frames):
        px = np.full((8, 8, 4 if with_alpha else 3), 128, np.uint8)
        iio.imwrite(folder / "images" / f"f{i}.png", px)
        m = look_at([0, -3, 0.5 * i], [0, 0, 0], [0, 0, 1])
        frames.append({"file_path": f"./images/f{i}", "transform_matrix": (m @ np.diag([-1, 1, -1, 1])).tolist()})
    path = folder / "transforms_train.json"
    path.write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return path


def test_cli_geometry_reports_bad_input(tmp_path, capsys):
    from vq_mitsuba.cli import main

    no_alpha = _write_json_capture(tmp_path / "rgb", with_alpha=False)
    # (neus.background auto would reconstruct it without masks: tests/geometry/test_maskfree.py)
    assert main(["geometry", str(no_alpha), "-o", str(tmp_path / "run"), "--quiet",
                 "--set", "neus.background=masks"]) == 2
    err = capsys.readouterr().err
    assert "alpha" in err and "transforms_train.json" in err
    assert not (tmp_path / "run" / "mesh.ply").exists()

    no_frames = tmp_path / "empty" / "transforms_train.json"
    no_frames.parent.mkdir()
    no_frames.write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    assert main(["geometry", str(no_frames), "-o", str(tmp_path / "run2"), "--quiet"]) == 2
    assert "no cameras" in capsys.readouterr().err

    assert main(["geometry", str(no_alpha), "-o", str(tmp_path / "run3"), "--set", "neus.bogus=1"]) == 2
    assert "unknown config key" in capsys.readouterr().err


def test_cli_fit_geometry_given_without_mesh_is_refused(tmp_path, capsys):
    from vq_mitsuba.cli import main

    capture = _write_json_capture(tmp_path / "cap", with_alpha=True)
    assert main(["fit", str(capture), "-o", str(tmp_path / "run"), "--geometry", "given", "--quiet"]) == 2
    assert "geometry" in capsys.readouterr().err


def test_capture_has_geometry_reads_no_images(tmp_path):
    from vq_mitsuba.data.captures import open_capture

    def capture_has_geometry(path):
        return open_capture(path).has_geometry()

    capture = _write_json_capture(tmp_path / "cap", with_alpha=True)
    assert capture_has_geometry(capture) is False
    trimesh.creation.icosphere(subdivisions=1).export(capture.parent / "mesh.ply")
    assert capture_has_geometry(capture.parent) is True
    xml = tmp_path / "scene.xml"
    xml.write_text('<scene version="3.0.0"><sensor type="perspective" id="a"/></scene>')
    assert capture_has_geometry(xml) is False
    xml.write_text('<scene version="3.0.0"><sensor type="perspective" id="a"/><shape type="sphere"/></scene>')
    assert capture_has_geometry(xml) is True


def test_cli_fit_refuses_mesh_with_geometry_neus(tmp_path, capsys):
    from vq_mitsuba.cli import main

    capture = _write_json_capture(tmp_path / "cap", with_alpha=True)
    mesh = tmp_path / "m.ply"
    trimesh.creation.icosphere(subdivisions=1).export(mesh)
    assert main(["fit", str(capture), "-o", str(tmp_path / "run"), "--geometry", "neus", "--mesh", str(mesh),
                 "--quiet"]) == 2
    assert "--geometry neus" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_one_config_file_holds_the_material_and_the_neus_sections(tmp_path):
    path = tmp_path / "both.yaml"
    path.write_text("train:\n  iterations: 7\nneus:\n  iterations: 5\n")
    assert load_config(path).train.iterations == 7
    assert load_config(path).neus.iterations == 5
    bad = tmp_path / "bad.yaml"
    bad.write_text("neus: [1, 2\n")
    with pytest.raises(InputError, match="bad.yaml"):
        load_config(bad)


def test_reflecting_colour_network_sees_the_mirror_direction():
    """neus.reflect: the colour network's direction input is the view direction mirrored about
    the normal (a ray going down-right onto an upward normal leaves up-right), after their cosine."""
    cfg = NeuSConfig(reflect=True)
    net = ColorNetwork(cfg)
    seen = []
    net.net[0].register_forward_hook(lambda mod, inp, out: seen.append(inp[0].detach()))
    feat = torch.zeros(1, cfg.geo_features)
    normal = torch.tensor([[0.0, 0.0, 1.0]])
    view = torch.tensor([[1.0, 0.0, -1.0]]) / 2 ** 0.5
    net(feat, normal, view)
    x = seen[0][0]
    start = cfg.geo_features + 3  # after the features and the normal
    assert x[start].item() == pytest.approx(-(0.5 ** 0.5))
    assert torch.allclose(x[start + 1:start + 4], torch.tensor([1.0, 0.0, 1.0]) / 2 ** 0.5, atol=1e-6)
    plain = ColorNetwork(NeuSConfig(reflect=False))
    assert plain.net[0].in_features == net.net[0].in_features - 1


def test_a_checkpoint_from_before_neus_reflect_counts_as_made_without_it(tmp_path):
    from vq_mitsuba.geometry.neus import check_architecture

    saved = {k: v for k, v in dataclasses.asdict(small_cfg(reflect=False)).items() if k != "reflect"}
    check_architecture(tmp_path / "neus.pt", saved, small_cfg(reflect=False))
    with pytest.raises(InputError, match="neus.reflect=False"):
        check_architecture(tmp_path / "neus.pt", saved, small_cfg(reflect=True))
    with pytest.raises(InputError, match="neus.max_res=24 \\(now 32\\)"):
        check_architecture(tmp_path / "neus.pt", saved, small_cfg(reflect=False, max_res=32))


def test_rate_spread_finds_a_slowed_stretch_of_training():
    # 10 steps/s for 60 s, then 5 steps/s for 30 s (as when another process takes half the CPU).
    steady = [{"step": 10 * t, "seconds": float(t)} for t in range(0, 61)]
    slowed = [{"step": 600 + 5 * t, "seconds": 60.0 + t} for t in range(1, 31)]
    spread = rate_spread(steady + slowed, window_s=30.0)
    assert spread["max"] == pytest.approx(10.0) and spread["min"] == pytest.approx(5.0)
    assert spread["median"] == pytest.approx(10.0)
    assert rate_spread(steady[:20], window_s=30.0)["min"] == pytest.approx(10.0)  # a tail of 19 s counts
    assert rate_spread(steady[:10], window_s=30.0) is None  # 9 s: too short to tell
    # A slowdown in the last, shorter stretch is found too.
    tail = [{"step": 600 + 5 * t, "seconds": 60.0 + t} for t in range(1, 21)]
    assert rate_spread(steady + tail, window_s=30.0)["min"] == pytest.approx(5.0)


def test_train_callback_at_the_start_and_every_interval_outside_the_training_clock(tmp_path):
    """`callback` sees the initialisation (step 0) and then the model every `callback_every_s`
    training seconds; its own time (here 0.2 s a call) is not training time."""
    import time

    capture = sphere_capture(n_views=6, size=16)
    calls = []

    def callback(neus, step, seconds):
        calls.append((step, seconds))
        time.sleep(0.2)

    neus = neus_for(capture, small_cfg(iterations=30))
    t0 = time.perf_counter()
    summary = train(neus, callback=callback, callback_every_s=0.05)
    wall = time.perf_counter() - t0
    assert calls[0] == (0, 0.0) and len(calls) >= 2
    assert [s for s, _ in calls] == sorted(s for s, _ in calls) and calls[-1][0] <= 30
    assert all(seconds >= 0.05 for _, seconds in calls[1:])
    assert summary["iterations"] == 30
    assert summary["train_seconds"] <= wall - 0.2 * len(calls) + 0.01


def test_the_colour_network_skips_samples_of_negligible_weight_and_the_colour_hardly_moves(monkeypatch):
    """Samples whose compositing weight is at most COLOR_MIN_WEIGHT are shaded black without the
    colour network: on a trained sphere most of them, and each ray's colour moves by at most the
    weight the skipped samples carry."""
    from vq_mitsuba.geometry.neus import renderer

    capture = sphere_capture(n_views=8, size=24)
    neus = neus_for(capture, small_cfg(iterations=120, seed=2))
    train(neus, None)
    lw = [1.0] * neus.cfg.levels
    neus.refresh_occupancy(lw)
    o, d = neus.rays_o[::3], neus.rays_d[::3]
    near, far = neus.intervals(o, d)
    shaded = {}
    calls = []
    colour = neus.model.color.forward
    monkeypatch.setattr(neus.model.color, "forward", lambda *a: calls.append(len(a[0])) or colour(*a))
    for threshold in (0.0, renderer.COLOR_MIN_WEIGHT):
        monkeypatch.setattr(renderer, "COLOR_MIN_WEIGHT", threshold)
        torch.manual_seed(0)
        with torch.no_grad():
            shaded[threshold] = neus.render(o, d, lw, neus.cfg.n_samples, True, False, near=near, far=far)["rgb"]
    everything, skipped = calls
    assert skipped < 0.6 * everything  # the trained surface concentrates the weight
    bound = neus.cfg.n_samples * renderer.COLOR_MIN_WEIGHT
    diff = (shaded[0.0] - shaded[renderer.COLOR_MIN_WEIGHT]).abs()
    assert float(diff.max()) <= bound and float(diff.max()) > 0
