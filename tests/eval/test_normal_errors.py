"""Shading-normal error per object: over the surface and in the views (what the material stage sees)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from vq_mitsuba.data.cameras import Camera, look_at
from vq_mitsuba.eval.normals import scene_object_labels, view_normal_errors
from vq_mitsuba.geometry.mesh import mesh_metrics


def two_spheres(tilt_deg_b: float = 0.0, radius_b: float = 0.3):
    """Sphere A at x=-0.5 and sphere B at x=+0.5 in one mesh, B's vertex normals tilted by tilt_deg_b;
    with the face label of each."""
    a = trimesh.creation.icosphere(subdivisions=4, radius=0.3)
    b = trimesh.creation.icosphere(subdivisions=4, radius=radius_b)
    a.apply_translation([-0.5, 0, 0])
    b.apply_translation([0.5, 0, 0])
    nb = np.asarray(b.vertex_normals).copy()
    if tilt_deg_b:
        axis = np.cross(nb, [0.0, 0.3, 1.0])
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        t = np.radians(tilt_deg_b)
        nb = nb * np.cos(t) + np.cross(axis, nb) * np.sin(t)
    mesh = trimesh.Trimesh(np.r_[a.vertices, b.vertices], np.r_[a.faces, b.faces + len(a.vertices)],
                           vertex_normals=np.r_[a.vertex_normals, nb], process=False)
    labels = np.r_[np.zeros(len(a.faces), int), np.ones(len(b.faces), int)]
    return mesh, labels


def cameras():
    return [Camera(f"c{i}", look_at(p, [0, 0, 0], [0, 0, 1]), 45.0, 48, 40)
            for i, p in enumerate(([0, -2.5, 0.5], [0.3, 2.5, 1.0], [0, -0.5, 2.6]))]


def test_per_object_errors_find_the_object_with_wrong_normals():
    gt, labels = two_spheres()
    pred, _ = two_spheres(tilt_deg_b=10.0)
    names = ["a", "b"]
    surface = mesh_metrics(pred, gt, n_points=20000, gt_face_labels=labels, label_names=names)["shading_normal_deg_by_object"]
    assert surface["a"]["median"] < 1.0 and 8.0 < surface["b"]["median"] < 11.0
    view = view_normal_errors(pred, gt, cameras(), labels, names)
    assert view["coverage"] == pytest.approx(1.0, abs=0.01)
    assert view["by_object"]["a"]["p90"] < 1.0
    assert 8.0 < view["by_object"]["b"]["median"] < 11.0
    assert view["by_object"]["a"]["count"] > 300 and view["by_object"]["b"]["count"] > 300
    same = view_normal_errors(gt, gt, cameras())
    assert same["p90"] < 0.1 and same["count"] == view["count"]


def test_in_view_error_counts_only_pixels_both_meshes_cover():
    gt, labels = two_spheres()
    small, _ = two_spheres(radius_b=0.15)  # B shrunk: its rim pixels hit only the true mesh
    view = view_normal_errors(small, gt, cameras(), labels, ["a", "b"])
    assert 0.6 < view["coverage"] < 0.95
    full = view_normal_errors(gt, gt, cameras(), labels, ["a", "b"])
    assert view["by_object"]["b"]["count"] < 0.5 * full["by_object"]["b"]["count"]
    with pytest.raises(ValueError):
        view_normal_errors(small, gt, cameras(), labels[:-1], ["a", "b"])
    with pytest.raises(ValueError):
        mesh_metrics(small, gt, n_points=2000, gt_face_labels=labels, label_names=["a"])


def test_scene_object_labels_group_numbered_shapes_of_one_material(tmp_path):
    shapes = [{"name": "base", "material": "wood", "faces": 3}, {"name": "stud_0", "material": "alu", "faces": 2},
              {"name": "stud_1", "material": "alu", "faces": 2}, {"name": "ball_0", "material": "red", "faces": 1},
              {"name": "ball_1", "material": "gold", "faces": 1}]
    (tmp_path / "scene.json").write_text(json.dumps({"shapes": shapes}))
    labels, names = scene_object_labels(tmp_path)
    assert labels.tolist() == [0, 0, 0, 1, 1, 2, 2, 3, 4]
    assert names == ["base", "stud", "stud", "ball_0", "ball_1"]
    assert scene_object_labels(tmp_path / "missing") is None
