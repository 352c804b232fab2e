"""Meshes from signed distance volumes: marching cubes, clean-up, and geometry metrics."""

from __future__ import annotations

import numpy as np


def marching_cubes(volume: np.ndarray, lo, hi, level: float = 0.0):
    """Triangle mesh of the `level` set of an SDF sampled on a regular grid (negative inside).

    volume[i, j, k] is the SDF at lo + (i, j, k) * (hi - lo) / (n - 1). Faces are oriented with
    normals pointing outwards (towards increasing SDF). Returns a trimesh.Trimesh.
    """
    import trimesh
    from skimage import measure

    volume = np.asarray(volume, dtype=np.float32)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if volume.ndim != 3 or min(volume.shape) < 2:
        raise ValueError("marching_cubes needs a 3-D volume of at least 2 samples per axis")
    if not (volume.min() < level < volume.max()):
        raise ValueError("the SDF volume has no zero crossing: the surface is empty")
    spacing = (hi - lo) / (np.asarray(volume.shape) - 1)
    verts, faces, _, _ = measure.marching_cubes(volume, level=level, spacing=tuple(spacing))
    mesh = trimesh.Trimesh(verts + lo, faces, process=True)
    if mesh.volume < 0:  # make normals point outwards whatever skimage's winding convention
        mesh.invert()
    return mesh


def component_sizes(mesh) -> np.ndarray:
    """Number of faces of each connected component (connectivity through shared vertices)."""
    import trimesh

    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    return np.bincount(labels)


def clean_mesh(mesh, min_component: float = 0.05, keep_largest: bool = False, smooth_iterations: int = 0,
               max_faces: int = 0):
    """Remove small pieces (fewer faces than min_component x the largest piece), or all but the
    largest piece, then optionally Taubin-smooth and decimate to max_faces; via pymeshlab."""
    import pymeshlab
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    sizes = np.bincount(labels)
    largest = int(sizes.max()) if len(sizes) else 0
    if keep_largest and len(sizes) > 1:  # exactly one piece, even when several share the largest size
        mesh = mesh.submesh([np.flatnonzero(labels == int(np.argmax(sizes)))], append=True)
    threshold = 0 if keep_largest else int(np.ceil(min_component * largest))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(mesh.vertices, dtype=np.float64),
                               face_matrix=np.asarray(mesh.faces, dtype=np.int32)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    if threshold > 1:
        ms.meshing_remove_connected_component_by_face_number(mincomponentsize=threshold, removeunref=True)
    ms.meshing_remove_unreferenced_vertices()
    if smooth_iterations > 0:
        ms.apply_coord_taubin_smoothing(stepsmoothnum=int(smooth_iterations))
    if max_faces and ms.current_mesh().face_number() > max_faces:
        ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(max_faces), preservenormal=True,
                                                    preservetopology=True, qualitythr=0.5)
    m = ms.current_mesh()
    out = trimesh.Trimesh(m.vertex_matrix().copy(), m.face_matrix().copy(), process=True)
    if out.volume < 0:
        out.invert()
    return out


def mesh_coverage(mesh, cameras, samples: int = 2) -> np.ndarray:
    """Each camera's coverage by the mesh: the share of samples x samples stratified rays per pixel
    whose primary ray hits it (Mitsuba ray casting), (N, H, W) float32 in [0, 1], as an alpha mask."""
    import mitsuba as mi

    from vq_mitsuba.backend import init_mitsuba
    from vq_mitsuba.data.cameras import camera_rays

    init_mitsuba()
    vertices = np.ascontiguousarray(np.asarray(mesh.vertices), dtype=np.float32)
    faces = np.ascontiguousarray(np.asarray(mesh.faces), dtype=np.uint32)
    shape = mi.Mesh("coverage", len(vertices), len(faces))
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(vertices.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    scene = mi.load_dict({"type": "scene", "mesh": shape})
    k = max(int(samples), 1)
    out = []
    for cam in cameras:
        n_px = cam.width * cam.height
        hits = np.zeros(n_px, np.float32)
        for sy in range(k):
            for sx in range(k):
                jitter = np.broadcast_to(np.array([(sx + 0.5) / k, (sy + 0.5) / k]), (n_px, 2))
                o, d = camera_rays(cam, jitter)
                ray = mi.Ray3f(mi.Point3f(*(o[:, i] for i in range(3))), mi.Vector3f(*(d[:, i] for i in range(3))))
                hits += np.array(scene.ray_test(ray), dtype=np.float32)
        out.append((hits / (k * k)).reshape(cam.height, cam.width))
    return np.stack(out).astype(np.float32)


def share_beneath(points: np.ndarray, n: np.ndarray, c: float, viewpoints: np.ndarray, tol: float) -> float:
    """The share of points (M, 3) more than tol beneath the plane n.x = c, on the side away from
    most of the viewpoints (N, 3): what the cameras saw under it (0 without points)."""
    if len(points) == 0:
        return 0.0
    up = 1.0 if np.mean(viewpoints @ n - c > 0) >= 0.5 else -1.0
    return float(np.mean(up * (points @ n - c) < -tol))


def support_plane(mesh, viewpoints: np.ndarray, radius: float = 1.0, tol: float = 0.02, min_share: float = 0.15,
                  seed: int = 0, points: np.ndarray | None = None,
                  max_below: float = 0.05) -> tuple[np.ndarray, float] | None:
    """The plane of a supporting surface (a table) in a mesh cropped to the sphere of `radius` at the
    origin: (unit normal n towards the viewpoints, offset c; the plane is n.x = c), or None.

    The plane holding the most surface area (faces within tol of it and facing along it; candidates
    from 300 faces drawn by area) counts as a support when it holds at least min_share of the area,
    runs out to the crop (its faces' 95th-percentile distance from the centre is at least 0.9 radius:
    a table goes on beyond the object, a flat face of the object stops short of the sphere), and
    nine in ten of the viewpoints (N, 3) lie on one side of it (cameras look down on a table; a
    face of the object is seen from both sides of its plane). With the capture's sparse points
    (M, 3) (SfM's, in the mesh's units), a candidate plane with more than max_below of those within
    1.5 radii beneath it (by over max(tol, 0.02 radius)) is no support: the cameras saw under it, so
    it is the flat top of a wide object (`support_from_points`)."""
    faces = np.asarray(mesh.faces)
    if len(faces) == 0 or len(viewpoints) == 0:
        return None
    centroids = np.asarray(mesh.triangles_center)
    normals = np.asarray(mesh.face_normals)
    area = np.asarray(mesh.area_faces)
    total = float(area.sum())
    if total <= 0:
        return None
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(faces), size=min(300, len(faces)), replace=False, p=area / total)
    views = np.asarray(viewpoints, np.float64)
    if points is not None:
        points = np.asarray(points, np.float64).reshape(-1, 3)
        points = points[np.linalg.norm(points, axis=1) < 1.5 * radius]
    below_tol = max(tol, 0.02 * radius)

    def seen_beneath(n: np.ndarray, c: float) -> bool:
        return points is not None and share_beneath(points, n, c, views, below_tol) > max_below

    best, best_area = None, 0.0
    for i in picks:
        n = normals[i]
        c = float(n @ centroids[i])
        if seen_beneath(n, c):
            continue
        inlier = (np.abs(centroids @ n - c) < tol) & (np.abs(normals @ n) > 0.9)
        a = float(area[inlier].sum())
        if a > best_area:
            best, best_area = (n, c, inlier), a
    if best is None or best_area < min_share * total:
        return None
    n, c, inlier = best
    # refit to the inliers (area-weighted least squares), then test the two other conditions
    w = area[inlier] / area[inlier].sum()
    mean = (w[:, None] * centroids[inlier]).sum(0)
    cov = ((centroids[inlier] - mean) * w[:, None]).T @ (centroids[inlier] - mean)
    n_fit = np.linalg.eigh(cov)[1][:, 0]
    n = n_fit if n_fit @ n >= 0 else -n_fit
    c = float(n @ mean)
    reach = float(np.percentile(np.linalg.norm(centroids[inlier], axis=1), 95))
    side = np.sign(views @ n - c)
    if reach < 0.9 * radius or max(np.mean(side > 0), np.mean(side < 0)) < 0.9 or seen_beneath(n, c):
        return None
    if np.mean(side > 0) < 0.5:
        n, c = -n, -c
    return n, c


def smooth_vertex_normals(mesh, iterations: int, max_angle_deg: float = 180.0):
    """The mesh with the same vertices and faces and smoothed vertex normals: each step replaces a
    vertex's normal by the renormalised mean of its own and those of its edge neighbours whose
    normals differ from it by less than max_angle_deg, so n steps average over about sqrt(n) edges
    within a smooth part and not across a crease (a small angle keeps a box's edges sharp while the
    bumps of the SDF grid on its faces are averaged away). The positions do not move (unlike Taubin
    smoothing), so the silhouette and the surface points stay where NeuS put them. The normals are
    stored in the mesh and written to PLY."""
    import scipy.sparse as sp
    import trimesh

    normals = np.asarray(mesh.vertex_normals, dtype=np.float64).copy()
    if iterations > 0 and len(mesh.faces):
        n_v = len(mesh.vertices)
        e = np.asarray(mesh.edges_unique)
        rows, cols = np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]]
        cos_min = np.cos(np.radians(min(max(max_angle_deg, 0.0), 180.0)))
        for _ in range(int(iterations)):
            w = (np.sum(normals[e[:, 0]] * normals[e[:, 1]], 1) >= cos_min).astype(np.float64)
            adj = sp.coo_matrix((np.r_[w, w], (rows, cols)), shape=(n_v, n_v)).tocsr() + sp.identity(n_v, format="csr")
            nxt = adj @ normals
            length = np.linalg.norm(nxt, axis=1, keepdims=True)
            normals = np.where(length > 1e-12, nxt / np.maximum(length, 1e-12), normals)
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), vertex_normals=normals, process=False)


def _sample(mesh, n: int, seed: int, faces: bool = False):
    """n surface points: positions, face normals, and shading normals (the vertex normals
    interpolated barycentrically, as the renderer shades); with faces=True also the face index of each."""
    import trimesh

    pts, face_idx = trimesh.sample.sample_surface(mesh, n, seed=seed)
    pts = np.asarray(pts)
    bary = trimesh.triangles.points_to_barycentric(np.asarray(mesh.triangles)[face_idx], pts)
    shading = np.einsum("nk,nkd->nd", bary, np.asarray(mesh.vertex_normals)[np.asarray(mesh.faces)[face_idx]])
    shading /= np.maximum(np.linalg.norm(shading, axis=1, keepdims=True), 1e-12)
    if faces:
        return pts, np.asarray(mesh.face_normals)[face_idx], shading, np.asarray(face_idx)
    return pts, np.asarray(mesh.face_normals)[face_idx], shading


def angle_stats(deg: np.ndarray) -> dict:
    """Mean, median and 90th percentile of angles in degrees (NaN when there are none), and their count."""
    deg = np.asarray(deg, dtype=np.float64)
    if deg.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "p90": float("nan"), "count": 0}
    return {"mean": float(deg.mean()), "median": float(np.median(deg)), "p90": float(np.percentile(deg, 90)),
            "count": int(deg.size)}


def check_face_labels(mesh, face_labels, names) -> np.ndarray:
    """face_labels as an array after checking it holds one label per face of mesh, each an index into names."""
    labels = np.asarray(face_labels)
    if len(labels) != len(mesh.faces) or names is None or labels.min() < 0 or labels.max() >= len(names):
        raise ValueError("gt_face_labels needs one label per ground-truth face, each indexing label_names")
    return labels


def per_label(deg: np.ndarray, labels: np.ndarray, names: list[str]) -> dict:
    """angle_stats of the angles of each label (labels index into names; names may repeat, to group labels)."""
    out = {}
    for name in dict.fromkeys(names):
        ids = [i for i, n in enumerate(names) if n == name]
        out[name] = angle_stats(deg[np.isin(labels, ids)])
    return out


def mesh_metrics(pred, gt, n_points: int = 100000, seed: int = 0, gt_face_labels: np.ndarray | None = None,
                 label_names: list[str] | None = None) -> dict:
    """Chamfer distance and normal consistency between two meshes, from surface samples.

    chamfer: mean of the two mean nearest-neighbour distances (pred->gt, gt->pred);
    chamfer_rel: the same as a fraction of the ground truth's bounding-box diagonal;
    normal_consistency: mean |cos| between each sample's normal and its nearest neighbour's,
    averaged over both directions (1 = identical orientation); f_score at 0.5% / 1% of the diagonal;
    shading_normal_deg_median / _p90: angle between the shading normals (interpolated vertex
    normals, what the material stage shades with) of each predicted sample and its nearest
    ground-truth sample (also their mean). With gt_face_labels (an object index per ground-truth
    face) and label_names (a name per index; equal names are one object), `shading_normal_deg_by_object`
    gives those statistics per object, each predicted sample counted for the object of its nearest
    ground-truth sample.
    """
    from scipy.spatial import cKDTree

    pa, na, sa = _sample(pred, n_points, seed)
    pb, nb, sb, fb = _sample(gt, n_points, seed + 1, faces=True)
    da, ia = cKDTree(pb).query(pa, workers=-1)  # pred -> gt
    db, ib = cKDTree(pa).query(pb, workers=-1)  # gt -> pred
    diag = float(np.linalg.norm(np.ptp(np.asarray(gt.vertices), axis=0)))
    nc = 0.5 * (np.abs(np.sum(na * nb[ia], -1)).mean() + np.abs(np.sum(nb * na[ib], -1)).mean())
    shading_deg = np.degrees(np.arccos(np.clip(np.sum(sa * sb[ia], -1), -1.0, 1.0)))
    out = {
        "chamfer": float(0.5 * (da.mean() + db.mean())),
        "chamfer_rel": float(0.5 * (da.mean() + db.mean()) / diag),
        "accuracy_rel": float(da.mean() / diag),  # pred -> gt
        "completeness_rel": float(db.mean() / diag),  # gt -> pred
        "normal_consistency": float(nc),
        "shading_normal_deg_mean": float(shading_deg.mean()),
        "shading_normal_deg_median": float(np.median(shading_deg)),
        "shading_normal_deg_p90": float(np.percentile(shading_deg, 90)),
        "bbox_diagonal": diag,
    }
    if gt_face_labels is not None:
        labels = check_face_labels(gt, gt_face_labels, label_names)
        out["shading_normal_deg_by_object"] = per_label(shading_deg, labels[fb][ia], list(label_names))
    for frac in (0.005, 0.01):
        tau = frac * diag
        prec, rec = float((da < tau).mean()), float((db < tau).mean())
        out[f"f_score@{frac:g}"] = 0.0 if prec + rec == 0 else 2 * prec * rec / (prec + rec)
    return out
