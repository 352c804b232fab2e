"""Mesh refinement inside Mitsuba: the vertices fitted jointly with the materials and the light.

After NeuS, the mesh is close but a fraction of a pixel off: a texture lands on different surface
points in different views, and shading normals carry the SDF's bumps. This stage moves the
vertices under the same photometric loss as the material fit, rendered with the same `principled`
BSDF and envmap:

- every step, the batch's primary rays are traced by Mitsuba against the current mesh (no
  gradients: which triangle each ray hits); the hit point is then recomputed in torch as the
  intersection of the ray with that triangle's current plane, and the shading normal as the
  barycentric blend of area-weighted vertex normals, so both are differentiable in the vertices;
- the vertices are parameterised as u = (I + lambda L) v (Nicolet et al. 2021, "Large Steps in
  Inverse Rendering of Geometry"; L the uniform Laplacian): Adam steps in u are smooth in v, so
  the mesh stays well shaped without a separate smoothness loss. The sparse system is factored
  once (cholespy) and solved twice per step (forward and backward).

Silhouettes are not differentiated (a pixel whose ray misses the mesh gives no gradient); the
stage corrects the surface where the images see it. The material field and envmap trained here
only serve the refinement; the material fit starts afresh on the refined mesh.
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.sparse as sp
import torch

from vq_mitsuba.backend import init_mitsuba, torch_device
from vq_mitsuba.config import Config
from vq_mitsuba.data.cameras import camera_rays
from vq_mitsuba.data.captures import Capture
from vq_mitsuba.models import losses
from vq_mitsuba.models.fields import EnvironmentMap
from vq_mitsuba.models.fitted import material_networks
from vq_mitsuba.render.shading import scene_for_mesh
from vq_mitsuba.run.loop import Budget, Loop, Progress
from vq_mitsuba.run.run_dir import RunDir

ENVMAP_HEIGHT = 32  # rows of the envmap learned beside the vertices


def uniform_laplacian(n_vertices: int, faces: np.ndarray) -> sp.csr_matrix:
    """L = D - A of the mesh's edge graph (each undirected edge once)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    a = (a + a.T).tocsr()
    a.data[:] = 1.0
    return (sp.diags(np.asarray(a.sum(1)).ravel()) - a).tocsr()


class SmoothParameterisation:
    """v <-> u = (I + lambda L) v, with v = solve(u) differentiable (the matrix is symmetric, so the
    backward pass is the same solve)."""

    def __init__(self, n_vertices: int, faces: np.ndarray, smoothness: float):
        from cholespy import CholeskySolverF, MatrixType

        m = (sp.identity(n_vertices, format="csr") + smoothness * uniform_laplacian(n_vertices, faces)).tocoo()
        self.matrix = m.tocsr()
        self.solver = CholeskySolverF(n_vertices, m.row.astype(np.int32), m.col.astype(np.int32),
                                      m.data.astype(np.float64), MatrixType.COO)

    def to_differential(self, v: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(self.matrix @ v.detach().cpu().numpy().astype(np.float64), dtype=torch.float32)

    def _solve(self, b: torch.Tensor) -> torch.Tensor:
        b = np.ascontiguousarray(b.detach().cpu().numpy(), dtype=np.float32)
        x = np.zeros_like(b)
        self.solver.solve(b, x)
        return torch.as_tensor(x)

    def from_differential(self, u: torch.Tensor) -> torch.Tensor:
        solve = self._solve

        class Solve(torch.autograd.Function):
            @staticmethod
            def forward(ctx, b):
                return solve(b).to(b.device)

            @staticmethod
            def backward(ctx, g):
                return solve(g).to(g.device)

        return Solve.apply(u)


def vertex_normals(v: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(V, 3) unit area-weighted vertex normals, differentiable in v."""
    fn = torch.linalg.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    n = torch.zeros_like(v).index_add_(0, faces.reshape(-1), fn.repeat_interleave(3, 0))
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def ray_triangle_hits(v: torch.Tensor, normals: torch.Tensor, faces: torch.Tensor, prim: torch.Tensor,
                      o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Hit points and shading normals of rays o + t d on the triangles `prim` (found by a tracer
    on a nearby state of the mesh): the ray's intersection with the triangle's current plane, and
    the barycentric blend of the vertex normals there, facing the ray. Differentiable in v."""
    f = faces[prim]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    fn = torch.linalg.cross(b - a, c - a)
    denom = (d * fn).sum(-1)
    denom = torch.where(denom.abs() < 1e-12, torch.full_like(denom, 1e-12), denom)
    t = ((a - o) * fn).sum(-1) / denom
    p = o + t[:, None] * d
    # barycentrics of p in the triangle (p lies in its plane)
    area2 = (fn * fn).sum(-1).clamp_min(1e-20)
    w_a = (torch.linalg.cross(c - b, p - b) * fn).sum(-1) / area2
    w_b = (torch.linalg.cross(a - c, p - c) * fn).sum(-1) / area2
    w_c = 1.0 - w_a - w_b
    n = w_a[:, None] * normals[f[:, 0]] + w_b[:, None] * normals[f[:, 1]] + w_c[:, None] * normals[f[:, 2]]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    n = torch.where(((n * d).sum(-1) > 0)[:, None], -n, n)
    return p, n


class UniformAdam(torch.optim.Optimizer):
    """Adam whose second moment is the largest over the whole parameter (Nicolet et al.): every
    coordinate's step is proportional to its own gradient, so vertices that a batch barely sees
    move barely, instead of a full step each as under per-coordinate Adam."""

    def __init__(self, params, lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self):
        for group in self.param_groups:
            b1, b2 = group["betas"]
            for q in group["params"]:
                if q.grad is None:
                    continue
                st = self.state[q]
                if not st:
                    st["t"], st["m"], st["v"] = 0, torch.zeros_like(q), torch.zeros_like(q)
                st["t"] += 1
                st["m"].mul_(b1).add_(q.grad, alpha=1 - b1)
                st["v"].mul_(b2).addcmul_(q.grad, q.grad, value=1 - b2)
                m_hat = st["m"] / (1 - b1 ** st["t"])
                v_max = float(st["v"].max()) / (1 - b2 ** st["t"])
                q.sub_(group["lr"] * m_hat / (math.sqrt(v_max) + group["eps"]))


class _RayPool:
    """Every opaque training pixel's ray (origin, direction) and target colour."""

    def __init__(self, capture: Capture, alpha_threshold: float, device):
        o_all, d_all, rgb_all = [], [], []
        for v, cam in enumerate(capture.cameras):
            opaque = np.flatnonzero(capture.alpha[v].reshape(-1) >= alpha_threshold)
            o, d = camera_rays(cam, pixels=opaque)
            o_all.append(o)
            d_all.append(d)
            rgb_all.append(capture.images[v].reshape(-1, 3)[opaque])
        self.o = torch.as_tensor(np.concatenate(o_all), device=device)
        self.d = torch.as_tensor(np.concatenate(d_all), device=device)
        self.rgb = torch.as_tensor(np.concatenate(rgb_all), dtype=torch.float32, device=device)

    def __len__(self) -> int:
        return len(self.o)


class MeshRefiner:
    """The vertices (through u), a material field and an envmap, fitted by one Adam."""

    def __init__(self, capture: Capture, mesh, cfg: Config):
        self.cfg, self.capture, rc = cfg, capture, cfg.refine
        init_mitsuba()
        self.device = device = torch_device()
        torch.manual_seed(cfg.train.seed)
        self.faces_np = np.asarray(mesh.faces, dtype=np.int64)
        self.faces = torch.as_tensor(self.faces_np, device=device)
        v0 = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
        self.param = SmoothParameterisation(len(v0), self.faces_np, rc.smoothness)
        self.u = torch.nn.Parameter(self.param.to_differential(v0).to(device))
        self.rays = _RayPool(capture, cfg.train.alpha_threshold, device)
        mean_fg = float(self.rays.rgb.mean())
        self.learn_env = capture.envmap is None
        if self.learn_env:
            self.env_module = EnvironmentMap(ENVMAP_HEIGHT, cfg.envmap.init_scale * max(mean_fg, 1e-3)).to(device)
            env_init = self.env_module().detach().cpu().numpy()
        else:
            self.fixed_env = torch.as_tensor(capture.envmap, device=device)
            env_init = capture.envmap
        self.scene = scene_for_mesh(mesh, env_init, capture.envmap_to_world)
        self.model, _ = material_networks(cfg, mesh, device)
        groups = [{"params": self.model.parameters(), "lr": cfg.train.lr}]
        if self.learn_env:
            groups.append({"params": self.env_module.parameters(), "lr": cfg.envmap.lr})
        self.optim = torch.optim.Adam(groups)
        self.base_lrs = [g["lr"] for g in self.optim.param_groups]
        self.optim_u = UniformAdam([self.u], rc.lr)
        self.gen = torch.Generator(device=device).manual_seed(cfg.train.seed)
        self.batch = min(cfg.train.batch_rays, len(self.rays))
        self.history: list[dict] = []
        self._acc = [0.0, 0]

    def vertices(self) -> torch.Tensor:
        return self.param.from_differential(self.u)

    def step(self, p: Progress) -> dict | None:
        cfg, rc = self.cfg, self.cfg.refine
        for g, lr in zip(self.optim.param_groups, self.base_lrs):
            g["lr"] = lr * rc.lr_end ** p.step_share
        # the vertices wait until the materials and the light explain the images roughly
        self.optim_u.param_groups[0]["lr"] = rc.lr * rc.lr_end ** p.step_share * float(p.share >= rc.warmup)
        self.model.set_progress(p.share, cfg.field.pe_anneal)
        v = self.vertices()
        self.scene.set_vertices(v.detach().cpu().numpy())
        idx = torch.randint(0, len(self.rays), (self.batch,), generator=self.gen, device=self.device)
        o, d = self.rays.o[idx], self.rays.d[idx]
        valid, prim = self.scene.trace_primitives(o.cpu().numpy(), d.cpu().numpy())
        o, d, prim, target = o[valid], d[valid], prim[valid], self.rays.rgb[idx][valid]
        pos, nrm = ray_triangle_hits(v, vertex_normals(v, self.faces), self.faces, prim, o, d)
        out = self.model(pos)
        env = self.env_module() if self.learn_env else self.fixed_env
        samples = self.scene.shade(pos, nrm, -d, out["basecolor"], out["metallic"], out["roughness"], env,
                                   cfg.train.spp, generator=self.gen, reduce=False, groups=2,
                                   material_fn=self.model if cfg.train.bounces > 0 else None)
        loss = losses.reconstruction_l2_decorrelated(samples, target, cfg.loss.gamma)
        loss = loss + cfg.loss.w_lam * losses.lambertian_prior(out["metallic"], out["roughness"],
                                                               cfg.loss.lam_metallic)
        self.optim.zero_grad(set_to_none=True)
        self.optim_u.zero_grad(set_to_none=True)
        loss.backward()
        params = [q for o in (self.optim, self.optim_u) for g in o.param_groups for q in g["params"]]
        if not all(torch.isfinite(q.grad).all() for q in params if q.grad is not None):
            return None  # a non-finite step is not applied
        self.optim.step()
        self.optim_u.step()
        with torch.no_grad():
            mse = float(losses.srgb_mse(samples.mean(1), target))
        self._acc = [self._acc[0] + mse, self._acc[1] + 1]
        if p.step % 50 == 0:
            self.history.append({"step": p.step, "psnr": losses.psnr(self._acc[0] / self._acc[1])})
            self._acc = [0.0, 0]
            return {"psnr": f"{self.history[-1]['psnr']:.2f}"}
        return None

    def refined_vertices(self) -> np.ndarray:
        with torch.no_grad():
            return self.vertices().cpu().numpy().astype(np.float64)


def refine_mesh(capture: Capture, mesh, cfg: Config, progress: bool = True):
    """The mesh with its vertices refined (same faces), and a summary for fit.json."""
    import trimesh

    t0 = time.perf_counter()
    refiner = MeshRefiner(capture, mesh, cfg)
    setup_s = time.perf_counter() - t0
    rc = cfg.refine
    result = Loop("refine", Budget(rc.iterations, rc.time_limit_s), refiner.step, progress_bar=progress).run()
    v = refiner.refined_vertices()
    moved = np.linalg.norm(v - np.asarray(mesh.vertices), axis=1)
    refined = trimesh.Trimesh(v, np.asarray(mesh.faces), process=False)
    diag = float(np.linalg.norm(np.ptp(np.asarray(mesh.vertices), axis=0)))
    summary = {"iterations": result.steps_this_call, "seconds": {"setup": setup_s, "train": result.seconds},
               "vertices": len(v), "moved_rel_diagonal": {"median": float(np.median(moved)) / diag,
                                                          "p99": float(np.percentile(moved, 99)) / diag},
               "final_psnr_train_batch": refiner.history[-1]["psnr"] if refiner.history else None}
    return refined, summary


def ensure_refined(capture_path, run: RunDir, cfg: Config, progress: bool = True) -> dict | None:
    """Refine the run's NeuS mesh once (refine.iterations > 0): mesh.ply becomes the refined mesh,
    with NeuS's vertex-normal smoothing applied as to NeuS's own; NeuS's is kept as mesh_neus.ply.
    Returns the stage's summary (None when it is off or already done, e.g. on resume)."""
    from vq_mitsuba.data.captures import load_capture
    from vq_mitsuba.geometry.mesh import smooth_vertex_normals

    # a material fit already started on NeuS's mesh (a run from before this stage) keeps that mesh
    if cfg.refine.iterations <= 0 or run.is_refined() or run.has_checkpoint():
        return None
    capture = load_capture(capture_path, options=cfg.capture, split="train", cache_dir=run.undistorted_dir)
    refined, summary = refine_mesh(capture, run.mesh(), cfg, progress=progress)
    if cfg.neus.normal_smoothing > 0:
        refined = smooth_vertex_normals(refined, cfg.neus.normal_smoothing, cfg.neus.normal_smoothing_angle)
    run.write_refined_mesh(refined, summary)
    return summary
