"""Shading-normal error of a reconstructed mesh in the views: what the material stage shades with.

Each pixel's ray is traced against the predicted and the true mesh with Mitsuba; where both are
hit, the angle between the two shading normals (interpolated vertex normals) is the pixel's error,
counted for the true object hit. Unlike errors from surface samples, this weighs the surface as
the cameras see it: hidden faces (the underside of an object on a table) do not count, and a
surface seen in many views counts more.
"""

from __future__ import annotations

import json
import re

import numpy as np

from vq_mitsuba.backend import init_mitsuba
from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.geometry.mesh import angle_stats, check_face_labels, per_label


def _scene(mesh):
    import mitsuba as mi

    from vq_mitsuba.render.shading import mesh_to_mitsuba

    normals = np.asarray(mesh.vertex_normals)
    return mi.load_dict({"type": "scene", "mesh": mesh_to_mitsuba(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                                                   normals)})


def _hits(scene, o: np.ndarray, d: np.ndarray):
    import drjit as dr
    import mitsuba as mi

    ray = mi.Ray3f(mi.Point3f(*(o[:, i].astype(np.float32) for i in range(3))),
                   mi.Vector3f(*(d[:, i].astype(np.float32) for i in range(3))))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    n = np.stack([np.array(c) for c in (si.sh_frame.n.x, si.sh_frame.n.y, si.sh_frame.n.z)], 1)
    prim = np.array(dr.select(si.is_valid(), si.prim_index, 0), dtype=np.int64)
    return valid, n, prim


def view_normal_errors(pred, gt, cameras, gt_face_labels: np.ndarray | None = None,
                       label_names: list[str] | None = None) -> dict:
    """Per-pixel shading-normal angle (degrees) between pred and gt (trimesh meshes in the cameras'
    world) over all pixels of `cameras` where both are hit: mean / median / p90 / count, the share of
    the true mesh's pixels the prediction also covers, and, with gt_face_labels and label_names
    (as in `mesh_metrics`), the same per object."""
    init_mitsuba()
    s_pred, s_gt = _scene(pred), _scene(gt)
    degs, labels, gt_pixels = [], [], 0
    for cam in cameras:
        o, d = camera_rays(cam)
        vp, np_, _ = _hits(s_pred, o, d)
        vg, ng, prim = _hits(s_gt, o, d)
        both = vp & vg
        gt_pixels += int(vg.sum())
        cos = np.clip(np.sum(np_[both] * ng[both], 1), -1.0, 1.0)
        degs.append(np.degrees(np.arccos(cos)))
        labels.append(prim[both])
    deg = np.concatenate(degs) if degs else np.zeros(0)
    out = angle_stats(deg)
    out["coverage"] = float(len(deg) / max(gt_pixels, 1))
    if gt_face_labels is not None:
        face_labels = check_face_labels(gt, gt_face_labels, label_names)
        out["by_object"] = per_label(deg, face_labels[np.concatenate(labels)], list(label_names))
    return out


def scene_object_labels(dataset) -> tuple[np.ndarray, list[str]] | None:
    """(object index per face of DATASET/mesh.ply, object names) of a bundled synthetic dataset, from
    its scene.json (the mesh is its shapes in order); shapes named NAME_<k> of one material count
    as one object NAME. None when the dataset does not list its shapes."""
    meta = DatasetDir(dataset).info_path
    if not meta.is_file():
        return None
    shapes = json.loads(meta.read_text()).get("shapes") or []
    if not shapes or any("faces" not in s for s in shapes):
        return None
    labels = np.concatenate([np.full(int(s["faces"]), i) for i, s in enumerate(shapes)])
    stem = [re.sub(r"_\d+$", "", s["name"]) for s in shapes]
    materials: dict[str, set] = {}
    for st, s in zip(stem, shapes):
        materials.setdefault(st, set()).add(s.get("material"))
    return labels, [st if len(materials[st]) == 1 else s["name"] for st, s in zip(stem, shapes)]
