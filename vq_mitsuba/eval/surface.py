"""Material error at the true surface: how much of the material gap is the geometry's.

The image-space scores of `evaluate` compare the maps rendered on the run's own mesh: where that
mesh is a fraction of a pixel off, a texture lands on other pixels, and a missing or swollen part
shows another object's material, so a geometry error is counted as a material error. Here each
test-view pixel is traced against the dataset's true mesh (DATASET/mesh.ply), with the same
stratified primary rays as the render (`aa` per pixel, the view's seed); each true hit point is
looked up at the nearest point of the run's mesh, the fitted material evaluated there, and the
pixel's average compared with its ground-truth maps exactly as the image-space score compares
them (basecolor after its own per-channel scale alignment, in sRGB; metallic and roughness
linearly; inside the ground-truth mask). On the true mesh both scores are the same figure; on a
reconstructed one, the image-space score minus this one is the share of the error that the
geometry causes, and this one is what the material field itself got wrong.

Nearest points are exact (`closest_points`): candidates from a k-d tree of the centroids of the
run's triangles, split until no edge is long, each candidate's exact closest point, and a wider
search wherever a closer triangle could have been missed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from vq_mitsuba import brdf
from vq_mitsuba.data.cameras import camera_rays, pixel_jitter, world_rotation
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.eval import input_scores, metrics as M

DATASET_MESH = DatasetDir.MESH  # the merged true mesh of a make-scene dataset, in its cameras' world
SAME_SURFACE_TOL = 1e-5  # meshes closer than this share of the diagonal everywhere are the same surface
QUERY_CHUNK = 16384


# --------------------------------------------------------------------------------------------
# Nearest points on a triangle mesh


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The closest point to p on each triangle (a, b, c), all (..., 3) broadcast together
    (Ericson, Real-Time Collision Detection, 5.1.5: the Voronoi regions of vertices, edges, face)."""
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    dot = lambda u, v: np.sum(u * v, -1)  # noqa: E731
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        face = a + ab * (vb / denom)[..., None] + ac * (vc / denom)[..., None]
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        t_ac = d2 / (d2 - d6)
        t_ab = d1 / (d1 - d3)
    out = np.where(np.isfinite(face), face, a)  # a degenerate triangle is its edges and vertices below
    # the regions in reverse order of Ericson's tests, so that his first match is applied last
    regions = [((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), lambda: b + (c - b) * t_bc[..., None]),
               ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda: a + ac * t_ac[..., None]),
               ((d6 >= 0) & (d5 <= d6), lambda: c + 0 * p),
               ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda: a + ab * t_ab[..., None]),
               ((d3 >= 0) & (d4 <= d3), lambda: b + 0 * p),
               ((d1 <= 0) & (d2 <= 0), lambda: a + 0 * p)]
    for inside, point in regions:
        q = point()
        out = np.where(inside[..., None] & np.isfinite(q), q, out)
    return out


class ClosestPoints:
    """Exact nearest points on a triangle mesh for many query points."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh
        from scipy.spatial import cKDTree

        vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
        edges = np.linalg.norm(vertices[faces] - vertices[np.roll(faces, 1, 1)], axis=-1)
        diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        # Long triangles are split (the surface is unchanged) so that nearest centroids find them.
        max_edge = max(2.0 * float(np.median(edges)), diag / 300.0, 1e-12)
        if edges.max() > max_edge:
            vertices, faces = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=max_edge, max_iter=12)
        self.triangles = vertices[faces]  # (F, 3, 3)
        centroids = self.triangles.mean(1)
        self.reach = float(np.linalg.norm(self.triangles - centroids[:, None], axis=-1).max())  # centroid -> vertex
        self.tree = cKDTree(centroids)

    def _nearest_of(self, q: np.ndarray, cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = self.triangles[cand]  # (n, k, 3, 3)
        pts = closest_on_triangles(q[:, None], t[..., 0, :], t[..., 1, :], t[..., 2, :])
        d = np.linalg.norm(pts - q[:, None], axis=-1)
        best = np.argmin(d, 1)
        rows = np.arange(len(q))
        return pts[rows, best], d[rows, best]

    def __call__(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nearest points (N, 3), their distances (N,)) of query points (N, 3)."""
        queries = np.asarray(queries, np.float64)
        points, dist = np.empty_like(queries), np.empty(len(queries))
        n_tri = len(self.triangles)
        for s in range(0, len(queries), QUERY_CHUNK):
            q = queries[s:s + QUERY_CHUNK]
            todo = np.arange(len(q))
            best_p, best_d = np.empty_like(q), np.full(len(q), np.inf)
            for k in (8, 64, 512):
                k = min(k, n_tri)
                dk, ik = self.tree.query(q[todo], k=k)
                dk, ik = dk.reshape(len(todo), k), ik.reshape(len(todo), k)
                p, d = self._nearest_of(q[todo], ik)
                better = d < best_d[todo]
                best_p[todo[better]], best_d[todo[better]] = p[better], d[better]
                # a triangle outside the k nearest centroids is at least dk[:, -1] - reach away
                todo = todo[(dk[:, -1] - self.reach < best_d[todo]) & (k < n_tri)]
                if len(todo) == 0:
                    break
            for i in todo:  # rare: every triangle whose centroid could still be within reach
                cand = np.asarray(self.tree.query_ball_point(q[i], best_d[i] + self.reach), np.int64)
                if len(cand):
                    p, d = self._nearest_of(q[i:i + 1], cand[None])
                    if d[0] < best_d[i]:
                        best_p[i], best_d[i] = p[0], d[0]
            points[s:s + QUERY_CHUNK], dist[s:s + QUERY_CHUNK] = best_p, best_d
        return points, dist


def same_surface(mesh_a, mesh_b, samples: int = 4096, seed: int = 0) -> bool:
    """Whether two trimesh meshes are one surface: surface samples of each lie on the other
    (within SAME_SURFACE_TOL of the diagonal), whatever their vertex order or triangulation."""
    import trimesh

    diag = float(np.linalg.norm(np.ptp(np.asarray(mesh_b.vertices), axis=0)))
    for x, y in ((mesh_a, mesh_b), (mesh_b, mesh_a)):
        pts, _ = trimesh.sample.sample_surface(x, samples, seed=seed)
        _, d = ClosestPoints(y.vertices, y.faces)(pts)
        if d.max() > SAME_SURFACE_TOL * max(diag, 1e-12):
            return False
    return True


# --------------------------------------------------------------------------------------------
# The score


def true_mesh_in(root: Path, cameras_world: str, run_world: str):
    """DATASET/mesh.ply in the run's world (it lies in the world of the dataset's cameras), or None."""
    from vq_mitsuba.data.captures import load_mesh

    path = Path(root) / DATASET_MESH
    if not path.is_file():
        return None
    mesh = load_mesh(path)
    mesh.vertices = np.asarray(mesh.vertices) @ world_rotation(cameras_world, run_world).T
    return mesh


@torch.no_grad()
def true_surface_maps(fitted, true_scene, camera, aa: int, seed: int, lookup: ClosestPoints) -> dict[str, np.ndarray]:
    """One view's maps at the true surface: `camera` (in the run's world) traced against the true
    mesh (`true_scene`, anything with `trace(origins, directions)`) with the render's stratified
    primary rays; each hit's material read at the nearest point of the run's mesh. basecolor
    (H, W, 3), metallic, roughness, hits (H, W) (rays that hit the true mesh), and the hits'
    distances to the run's mesh (D,)."""
    h, w = camera.height, camera.width
    n_pix = h * w
    rng = np.random.default_rng(seed)  # the offsets `render.views.Renderer` draws for this seed
    sums = np.zeros((n_pix, brdf.CHANNELS))
    count = np.zeros(n_pix)
    distances = []
    device = fitted.model.center.device
    for a in range(aa):
        o, d = camera_rays(camera, np.full((n_pix, 2), 0.5) if aa == 1 else pixel_jitter(n_pix, a, aa, rng))
        hits = true_scene.trace(o, d)
        idx = torch.nonzero(hits.valid)[:, 0]
        if len(idx) == 0:
            continue
        near, dist = lookup(hits.position[idx].double().cpu().numpy())
        out = fitted.materials_at(torch.as_tensor(near, dtype=torch.float32, device=device), ids=False)
        values = torch.cat([out[i.name].reshape(-1, i.channels) for i in brdf.INPUTS], 1)
        pix, values = idx.cpu().numpy(), values.double().cpu().numpy()
        for c in range(values.shape[1]):  # bincount, not np.add.at: the same sums, far faster
            sums[:, c] += np.bincount(pix, values[:, c], minlength=n_pix)
        count += np.bincount(pix, minlength=n_pix)
        distances.append(dist)
    mean = sums / np.maximum(count, 1)[:, None]
    maps, at = {}, 0
    for i in brdf.INPUTS:  # each input's columns of the sums, as an (h, w, 3) or (h, w) map
        maps[i.name] = mean[:, at:at + i.channels].reshape((h, w, 3) if i.colour else (h, w))
        at += i.channels
    return {**maps, "hits": count.reshape(h, w),
            "distance": np.concatenate(distances) if distances else np.zeros(0)}


def surface_material_scores(fitted, true_mesh, cameras: list, gts: list[dict], aa: int,
                            scale_method: str = "lstsq") -> dict:
    """Every BRDF input's scores (`input_scores`) of the fitted materials at the true surface
    points of every test view (`cameras` in the run's world, `gts` their ground truth as
    `evaluate.load_ground_truth` reads it, view i traced with seed i as `evaluate` renders it),
    and how far the true points lie from the run's mesh."""
    from vq_mitsuba.render.shading import scene_for_mesh

    lookup = ClosestPoints(fitted.mesh.vertices, fitted.mesh.faces)
    true_scene = scene_for_mesh(true_mesh, np.ones((2, 4, 3), np.float32), np.eye(4))  # traced only
    maps = [true_surface_maps(fitted, true_scene, cam, aa, i, lookup) for i, cam in enumerate(cameras)]
    masks = np.stack([g["mask"] for g in gts])
    scales = input_scores.alignment_scales(maps, gts, masks, scale_method)
    rows = [{**input_scores.view_scores(m, g, g["mask"], scales),
             "hit_share": float((m["hits"][g["mask"]] > 0).mean()) if g["mask"].any() else math.nan}
            for m, g in zip(maps, gts)]
    scores = input_scores.mean_scores(rows)
    for name, s in scales.items():
        scores[name].update(aligned_with=scale_method, scales=[float(x) for x in s])
    dist = np.concatenate([m["distance"] for m in maps])
    diag = float(np.linalg.norm(np.ptp(np.asarray(true_mesh.vertices), axis=0)))
    q = (lambda p: float(np.percentile(dist, p))) if len(dist) else (lambda p: math.nan)
    return {
        "what": "the fitted material at each test pixel's true surface points (DATASET/mesh.ply, the render's "
                "primary rays), looked up at the nearest point of the run's mesh, against the ground-truth maps "
                "as the image-space scores compare them: the image-space figure minus this one is the geometry's "
                "share of the error",
        **scores,
        "hit_share": M.mean_of(r["hit_share"] for r in rows),
        "distance": {"mean": float(dist.mean()) if len(dist) else math.nan, "median": q(50), "p90": q(90),
                     "true_mesh_diagonal": diag,
                     "what": "from each true hit point to the nearest point of the run's mesh, in the run's units"},
        "per_view": rows,
    }


def evaluate_surface(predictor, data, aa: int, scale_method: str) -> dict | None:
    """`surface_material_scores` for `evaluate`: for a fitted run (a predictor with `fitted`) on a
    dataset with a true mesh that the run's mesh is not; None otherwise."""
    fitted = getattr(predictor, "fitted", None)
    if fitted is None:
        return None
    true_mesh = true_mesh_in(data.root, data.cameras_world, predictor.world)
    if true_mesh is None or same_surface(fitted.mesh, true_mesh):
        return None
    return surface_material_scores(fitted, true_mesh, data.views, data.gts, aa, scale_method)
