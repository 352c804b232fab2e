"""The refinement stage: differentiable hits on a traced mesh, the smooth vertex parameterisation,
and vertices fitted back towards the true surface on a tiny capture."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla
import torch

from tiny_scene import write_sphere_capture


def _icosphere(radius=0.5, subdivisions=3):
    import trimesh

    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def test_ray_triangle_hits_match_mitsuba_and_finite_differences():
    from vq_mitsuba.engine.refine import ray_triangle_hits, vertex_normals
    from vq_mitsuba.render.shading import scene_for_mesh

    mesh = _icosphere()
    scene = scene_for_mesh(mesh, np.ones((8, 16, 3), np.float32), np.eye(4))
    rng = np.random.default_rng(0)
    o = np.tile(np.array([[0.1, -0.05, 2.0]], np.float32), (200, 1))
    d = np.stack([rng.uniform(-0.15, 0.15, 200), rng.uniform(-0.15, 0.15, 200), -np.ones(200)], -1)
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    valid, prim = scene.trace_primitives(o, d)
    assert valid.all()
    hits = scene.trace(o, d)
    v = torch.tensor(mesh.vertices, dtype=torch.float64, requires_grad=True)
    faces = torch.as_tensor(np.asarray(mesh.faces))
    ot, dt = torch.as_tensor(o, dtype=torch.float64), torch.as_tensor(d, dtype=torch.float64)
    p, n = ray_triangle_hits(v, vertex_normals(v, faces), faces, prim, ot, dt)
    # the same points Mitsuba hits, normals facing the camera and close to the interpolated ones
    np.testing.assert_allclose(p.detach().numpy(), hits.position.numpy(), atol=2e-5)
    assert ((n * dt).sum(-1) < 0).all()
    assert (torch.acos((n.float() * hits.normal).sum(-1).clamp(-1, 1)).rad2deg() < 3.0).all()
    # gradients in the vertices against central differences
    w = torch.randn(p.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))

    def objective(vv):
        pp, nn = ray_triangle_hits(vv, vertex_normals(vv, faces), faces, prim, ot, dt)
        return (w * pp).sum() + (w * nn).sum()

    objective(v).backward()
    touched = torch.unique(faces[prim].reshape(-1))[:6]
    for i in touched:
        for c in range(3):
            e = torch.zeros_like(v)
            e[i, c] = 1e-6
            fd = (objective(v.detach() + e) - objective(v.detach() - e)) / 2e-6
            assert abs(float(fd) - float(v.grad[i, c])) < 1e-5 * max(1.0, abs(float(fd)))


def test_smooth_parameterisation_round_trip_and_gradient():
    from vq_mitsuba.engine.refine import SmoothParameterisation

    mesh = _icosphere(subdivisions=2)
    param = SmoothParameterisation(len(mesh.vertices), np.asarray(mesh.faces), 10.0)
    v = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    u = param.to_differential(v).requires_grad_(True)
    back = param.from_differential(u)
    np.testing.assert_allclose(back.detach().numpy(), v.numpy(), atol=1e-5)
    g = torch.randn_like(v)
    (back * g).sum().backward()
    expected = spla.spsolve(param.matrix.tocsc(), g.numpy().astype(np.float64))
    np.testing.assert_allclose(u.grad.numpy(), expected, rtol=1e-3, atol=1e-5)
    # a step in u is smooth in v: a unit change of one u coordinate spreads over its neighbours
    e = torch.zeros_like(u)
    e[0, 0] = 1.0
    spread = param.from_differential(u.detach() + e) - back.detach()
    assert 0 < float(spread[0, 0]) < 0.5 and float((spread[:, 0].abs() > 1e-3).sum()) > 5


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    return write_sphere_capture(tmp_path_factory.mktemp("refine") / "sphere", size=40, n_views=16, spp=64)


def test_refinement_moves_a_dented_sphere_back_towards_the_true_one(sphere_capture):
    """A sphere whose top half is pushed in by 8 % (the silhouette from the side barely changes):
    fitting the vertices with the materials brings the surface and its normals back towards the
    true sphere seen in the images."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.engine.refine import refine_mesh

    capture = load_capture(sphere_capture)
    mesh = _icosphere()
    v = np.asarray(mesh.vertices).copy()
    v[:, 1] = np.where(v[:, 1] > 0, 0.92 * v[:, 1], v[:, 1])
    mesh.vertices = v
    cfg = load_config(None, ["refine.iterations=150", "train.batch_rays=1024", "refine.lr=3e-3"])

    def errors(m):
        r = np.linalg.norm(np.asarray(m.vertices), axis=1)
        n = np.asarray(m.vertex_normals)
        radial = np.asarray(m.vertices) / r[:, None]
        return np.abs(r - 0.5).mean(), np.degrees(np.arccos(np.clip((n * radial).sum(1), -1, 1))).mean()

    refined, summary = refine_mesh(capture, mesh, cfg, progress=False)
    before, after = errors(mesh), errors(refined)
    assert summary["iterations"] == 150
    assert after[0] < 0.7 * before[0], (before, after)
    assert after[1] < 0.7 * before[1], (before, after)
