"""The material score at the true surface (eval/surface.py): exact nearest points, the same figure
as the image-space score on the true mesh, and a separate block for a run on another mesh."""

import json
import math

import numpy as np
import pytest

from vq_mitsuba.eval.surface import ClosestPoints, closest_on_triangles, same_surface


def _dense_triangle_min(p, tri, n=400):
    """Smallest distance from p to a dense barycentric grid of the triangle (an upper bound)."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    keep = u + v <= 1
    pts = tri[0] + u[keep, None] * (tri[1] - tri[0]) + v[keep, None] * (tri[2] - tri[0])
    return np.linalg.norm(pts - p, axis=-1).min()


def test_closest_point_on_a_triangle_in_every_region():
    rng = np.random.default_rng(0)
    for _ in range(60):
        tri = rng.normal(size=(3, 3))
        p = rng.normal(size=3) * 2
        q = closest_on_triangles(p, tri[0], tri[1], tri[2])
        # q lies on the triangle: its barycentric coordinates are inside [0, 1]
        m = np.stack([tri[1] - tri[0], tri[2] - tri[0]], 1)
        bary, *_ = np.linalg.lstsq(m, q - tri[0], rcond=None)
        assert bary.min() > -1e-9 and bary.sum() < 1 + 1e-9
        assert np.linalg.norm(m @ bary + tri[0] - q) < 1e-9
        d = np.linalg.norm(q - p)
        dense = _dense_triangle_min(p, tri)
        assert d <= dense + 1e-12 and dense - d < 0.01 * max(1.0, d)


def test_nearest_points_on_a_mesh_match_brute_force():
    """Small triangles beside one long one (as a floor under objects): every query's nearest point
    is the brute-force one."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    floor_v = np.array([[-5.0, -0.31, -5.0], [5.0, -0.31, -5.0], [0.0, -0.31, 5.0]])
    vertices = np.concatenate([sphere.vertices, floor_v])
    faces = np.concatenate([sphere.faces, [[len(sphere.vertices), len(sphere.vertices) + 1,
                                            len(sphere.vertices) + 2]]])
    rng = np.random.default_rng(1)
    queries = np.concatenate([rng.normal(size=(300, 3)) * 0.5, rng.uniform(-3, 3, size=(100, 3)) * [1, 0.05, 1]])
    points, dist = ClosestPoints(vertices, faces)(queries)
    tri = vertices[faces]
    brute = closest_on_triangles(queries[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    brute_d = np.linalg.norm(brute - queries[:, None], axis=-1).min(1)
    np.testing.assert_allclose(dist, brute_d, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(points - queries, axis=-1), dist, atol=1e-9)


def test_same_surface_ignores_triangulation_but_not_an_offset():
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    shuffled = trimesh.Trimesh(mesh.vertices, mesh.faces[np.random.default_rng(0).permutation(len(mesh.faces))],
                               process=False)
    finer = mesh.subdivide()  # the same flat triangles, split
    moved = trimesh.Trimesh(mesh.vertices * 1.001, mesh.faces, process=False)
    assert same_surface(mesh, shuffled) and same_surface(mesh, finer)
    assert not same_surface(mesh, moved)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from vq_mitsuba.synthetic.mitsuba_scenes import make_scene

    return make_scene("demo", tmp_path_factory.mktemp("data") / "demo", resolution=20, n_train=4, n_test=2, spp=8)


FIT = ["--set", "train.iterations=30", "--set", "train.batch_rays=256", "--set", "residual.iterations=0",
       "--set", "vq.enabled=false"]


def test_on_the_true_mesh_it_is_the_image_space_score(dataset, tmp_path):
    """A run fitted on the dataset's own geometry (its XML, Mitsuba world): the score at the true
    surface equals the image-space one, and eval leaves the block out."""
    from vq_mitsuba.cli import main
    from vq_mitsuba.eval.evaluate import _load_test_views
    from vq_mitsuba.eval.surface import surface_material_scores, true_mesh_in
    from vq_mitsuba.run.run_dir import RunDir

    run = tmp_path / "run"
    assert main(["fit", str(dataset / "scene.xml"), "-o", str(run), "--quiet", *FIT]) == 0
    out = tmp_path / "metrics.json"
    assert main(["eval", str(run), "--gt", str(dataset), "--spp", "4", "--quiet", "-o", str(out),
                 "--meanshift", "none"]) == 0
    m = json.loads(out.read_text())
    assert m["surface_material"] is None
    fitted = RunDir(run).load()
    data = _load_test_views(dataset, fitted.world)
    true_mesh = true_mesh_in(dataset, data.cameras_world, fitted.world)
    s = surface_material_scores(fitted, true_mesh, data.views, data.gts, m["render"]["aa"])
    assert s["distance"]["p90"] < 1e-5 * s["distance"]["true_mesh_diagonal"]
    assert s["hit_share"] > 0.95
    for key in ("basecolor", "metallic", "roughness"):
        assert math.isfinite(m[key]["psnr"])
        assert s[key]["psnr"] == pytest.approx(m[key]["psnr"], abs=0.05)
    assert s["basecolor"]["scales"] == pytest.approx(m["alignment"]["scales"], rel=1e-3)


def test_on_another_mesh_eval_reports_it_with_the_distances(dataset, tmp_path, capsys):
    """A run fitted on the true mesh swollen by a known offset along its normals (Blender world,
    from the json capture): eval writes the block, and the true points lie that offset away."""
    import trimesh

    from vq_mitsuba.cli import main

    true_mesh = trimesh.load(dataset / "mesh.ply", process=False)
    offset = 0.01
    swollen = trimesh.Trimesh(true_mesh.vertices + offset * true_mesh.vertex_normals, true_mesh.faces,
                              process=False)
    swollen.export(tmp_path / "swollen.ply")
    run = tmp_path / "run"
    assert main(["fit", str(dataset / "transforms_train.json"), "--mesh", str(tmp_path / "swollen.ply"),
                 "-o", str(run), "--quiet", *FIT]) == 0
    out = tmp_path / "metrics.json"
    assert main(["eval", str(run), "--gt", str(dataset), "--spp", "4", "--quiet", "-o", str(out),
                 "--meanshift", "none"]) == 0
    assert "materials at the true surface" in capsys.readouterr().out
    s = json.loads(out.read_text())["surface_material"]
    assert s is not None and s["hit_share"] > 0.95
    assert s["distance"]["median"] == pytest.approx(offset, rel=0.1)
    for key in ("basecolor", "metallic", "roughness"):
        assert math.isfinite(s[key]["psnr"])
    assert len(s["per_view"]) == 2
