"""The Lambertian prior's metallic term weighed by what the images say (`loss.prior_evidence`).

The prior pulls every surface towards a dielectric whether or not the images object. They can: a
dielectric's highlight is the colour of the light (its specular reflection is untinted), so on a
coloured dielectric the brightest views of a point are paler than its typical view; a metal's
highlight is the colour of the metal, as saturated as the rest of it.

Before the first step, `HITS` training hits are read in up to `VIEWS` of the views that face
them (unoccluded, within `FACING` of the normal, on opaque pixels: no silhouette pixel mixed with
what lies behind; `sample_views`). A hit gives evidence where it has a highlight (in `RANK` + 1
views at least `HIGHLIGHT` times its median view's luminance: one bright view is as likely a
misregistered shadow edge) on a coloured surface (the median view's chromatic saturation at least
`COLOURED`); its evidence is how much of the surface's colour the highlight keeps, its tint
(`highlight_tint`): white light added to a colour divides its saturation by the growth of the
channel sum, so a dielectric's highlight, however faint, has tint 0 and a metal's 1. The tints are
averaged over a coarse voxel grid on the object (`WeightGrid`, voxels where at least
`MIN_EVIDENCE` hits and `MIN_SHARE` of the hits read give evidence: a few bright views of a
painted surface that keep its colour, as on DTU scan24, are not a metal); a voxel's weight of
the metallic term is 1 up to a tint of `DIELECTRIC` (paler highlights: the images side with the
prior), 0 from `METAL` (highlights that keep the colour: the images say metal), linear between,
and 1 where there is no evidence (grey surfaces, no highlight: the images do not say, and the
prior decides as before). Every hit of a step looks its voxel up. The roughness term is left
whole.

Brightness alone also finds shading and texture: a pixel of one view lands on a texture's bright
tone where another view's lands on its dark tone, and a shadow's edge moves within a pixel's
footprint from view to view, both brighter in the surface's own colour. A highlight is told by
where it sits: about the mirror direction of the bright parts of the light.
Once the light is known (the capture's, or the learned one at `READ_AT` of the schedule, after
which the light has its bright parts in place), a hit's evidence is kept only where its brightness
over its views follows the light seen about each view's mirror direction (the view reflected
about the normal; the light averaged over `LOBE_ROWS` rows): a rank correlation of at least
`MIRROR` (`at_mirror`). The grid is built again from the hits that keep it (`PriorReading`).

A capture with no voxel below 1 fits exactly as without the rule; `benchmarks/results/prior_evidence/`.
"""

from __future__ import annotations

import numpy as np
import torch

from vq_mitsuba.data.cameras import BLENDER_ENV_TO_WORLD
from vq_mitsuba.data.imageio import LUMINANCE

HITS = 16384  # training hits read in several views
VIEWS = 16  # views per hit
MIN_VIEWS = 4  # a hit seen in fewer views gives no evidence
RANK = 1  # the highlight is read in the views sorted by luminance at this rank (0: the brightest)
FACING = 0.35  # cosine between the normal and a view from which the hit is read there (no silhouette pixels)
OPAQUE = 0.99  # alpha from which a pixel is read (no pixel mixed with what lies behind)
HIGHLIGHT = 1.5  # brightest over median view luminance from which a hit has a highlight
COLOURED = 0.08  # chromatic saturation of the median view from which a surface is coloured
DIELECTRIC = 0.55  # highlight tint up to which the metallic term is whole
METAL = 0.8  # highlight tint from which the metallic term is off
GRID = 24  # voxels along the object's longest side
MIN_EVIDENCE = 3  # hits with a highlight that a voxel needs to give evidence
MIN_SHARE = 0.35  # and the share of the voxel's hits read that they must be at least
READ_AT = 0.2  # schedule share at which the highlights are read again against the learned light
MIRROR = 0.0  # rank correlation with the light about the views' mirror directions from which a hit has a highlight
LOBE_ROWS = 16  # rows of the light averaged for the mirror directions (about 11 deg a texel)


class ViewSamples:
    """Where each of P hits is seen: `view` (P, K) view indices, -1 where none; `rgb` (P, K, 3) the
    images' linear colour at the hit's pixel there (NaN where none)."""

    def __init__(self, view: torch.Tensor, rgb: torch.Tensor):
        self.view, self.rgb = view, rgb

    @property
    def valid(self) -> torch.Tensor:
        return self.view >= 0

    @property
    def lum(self) -> torch.Tensor:
        """(P, K) luminance (NaN where not seen)."""
        return self.rgb @ torch.tensor(LUMINANCE)

    def seen(self) -> torch.Tensor:
        """(P,) bool: the hit is seen in at least MIN_VIEWS views."""
        return self.valid.sum(1) >= MIN_VIEWS


def sample_views(scene, capture, positions: torch.Tensor, normals: torch.Tensor, alpha_threshold: float,
                 seed: int, views: int = VIEWS) -> ViewSamples:
    """The views that see each hit (positions, normals (P, 3)), `views` of them at most, drawn at
    random, and the images' colour at each hit's pixel there."""
    p = positions.detach().cpu().double().numpy()
    n = normals.detach().cpu().float().numpy()
    extent = float(np.ptp(p, 0).max()) if len(p) else 1.0
    n_views = len(capture.cameras)
    seen = np.zeros((len(p), n_views), bool)
    rgb = np.zeros((len(p), n_views, 3), np.float32)
    for v, cam in enumerate(capture.cameras):
        d = p - cam.origin
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        ok = (n * -d).sum(1) > FACING
        hits = scene.trace(np.ascontiguousarray(np.broadcast_to(cam.origin, p.shape), np.float32),
                           d.astype(np.float32))
        ok &= hits.valid.cpu().numpy() & (np.linalg.norm(hits.position.cpu().numpy() - p, axis=1) < 2e-3 * extent)
        xy = cam.project(p)
        xi, yi = np.floor(xy[:, 0]).astype(np.int64), np.floor(xy[:, 1]).astype(np.int64)
        ok &= (xi >= 0) & (yi >= 0) & (xi < capture.width) & (yi < capture.height)
        xi, yi = np.clip(xi, 0, capture.width - 1), np.clip(yi, 0, capture.height - 1)
        ok &= capture.alpha[v, yi, xi] >= max(alpha_threshold, OPAQUE)
        seen[:, v], rgb[:, v] = ok, capture.images[v, yi, xi]
    # `views` of each hit's views at random: the largest random keys among those that see it
    keys = np.where(seen, np.random.default_rng(seed).random(seen.shape), -1.0)
    pick = np.argsort(-keys, axis=1)[:, :min(views, n_views)]
    ok = np.take_along_axis(seen, pick, 1)
    rows = np.arange(len(p))[:, None]
    return ViewSamples(torch.as_tensor(np.where(ok, pick, -1)),
                       torch.as_tensor(np.where(ok[..., None], rgb[rows, pick], np.nan).astype(np.float32)))


def saturation(rgb: torch.Tensor) -> torch.Tensor:
    """Chromatic saturation of linear colours (..., 3): the distance of the chromaticity r, g, b
    over their sum from grey (0 for grey, 0.82 for a pure primary)."""
    total = rgb.clamp_min(0).sum(-1, keepdim=True)
    return (rgb.clamp_min(0) / total.clamp_min(1e-8) - 1.0 / 3.0).norm(dim=-1)


def ranked_views(samples: ViewSamples) -> tuple[torch.Tensor, torch.Tensor]:
    """(P,) each hit's bright view (at RANK by luminance) and median view, as columns of `samples`."""
    lum = samples.lum
    order = torch.argsort(torch.nan_to_num(lum, nan=-1.0), dim=1, descending=True)
    rows = torch.arange(len(lum))
    return order[:, RANK], order[rows, samples.valid.sum(1) // 2]


def highlight_tint(samples: ViewSamples) -> torch.Tensor:
    """(P,) how much of its colour each hit's highlight keeps: 0 where the bright view is the
    median view's colour plus white light (a dielectric's untinted reflection: the saturation falls
    as the channel sum grows), 1 where it keeps the median view's saturation (a metal's); NaN where
    the hit gives no evidence (seen in fewer than MIN_VIEWS views, no highlight, a grey surface)."""
    lum = samples.lum
    n = samples.valid.sum(1)
    bright, median = ranked_views(samples)
    rows = torch.arange(len(lum))
    rgb_bright, rgb_median = samples.rgb[rows, bright], samples.rgb[rows, median]
    l_bright, l_median = lum[rows, bright], lum[rows, median]
    s_bright, s_median = saturation(rgb_bright), saturation(rgb_median)
    evidence = (n >= MIN_VIEWS) & (l_bright >= HIGHLIGHT * l_median) & (l_median > 0) & (s_median >= COLOURED)
    # white added to a colour scales its saturation by the ratio of the channel sums
    white = (rgb_median.clamp_min(0).sum(-1) / rgb_bright.clamp_min(0).sum(-1).clamp_min(1e-8)).clamp(max=0.95)
    kept = (s_bright / s_median.clamp_min(1e-8) - white) / (1.0 - white)
    return torch.where(evidence, kept, torch.full((), float("nan")))


def lobe_light(env: torch.Tensor, rows: int = LOBE_ROWS) -> np.ndarray:
    """(rows, 2 rows) luminance of a lat-long light (H, W, 3), averaged over texel blocks."""
    lum = env.detach().float().cpu() @ torch.tensor(LUMINANCE, dtype=torch.float32)
    return torch.nn.functional.adaptive_avg_pool2d(lum[None, None], (rows, 2 * rows))[0, 0].numpy()


def mirror_light(light: np.ndarray, positions: np.ndarray, normals: np.ndarray, origins: np.ndarray,
                 to_env: np.ndarray) -> np.ndarray:
    """(P,) the light's luminance (`lobe_light`) about the mirror direction of the view from camera
    `origins` (P, 3) to each hit (positions, normals (P, 3)) about its normal; `to_env` (3, 3)
    turns world directions into the light's (`vq_mitsuba.data.envmaps` convention)."""
    from vq_mitsuba.data.envmaps import direction_to_uv

    w = origins - positions
    w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12)
    n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    r = 2.0 * (n * w).sum(1, keepdims=True) * n - w
    u, v = direction_to_uv(r @ to_env.T)
    h, wd = light.shape
    return light[np.clip((v * h).astype(np.int64), 0, h - 1), np.clip((u * wd).astype(np.int64), 0, wd - 1)]


def rank_correlation(a: np.ndarray, b: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(P,) Spearman correlation of each row of a and b (P, K) over its valid entries (ties share
    their mean rank; NaN with fewer than MIN_VIEWS or no spread)."""
    from scipy.stats import rankdata

    ranks = [np.where(valid, rankdata(np.where(valid, x, np.inf), axis=1), 0.0) for x in (a, b)]
    count = valid.sum(1)
    mean = [r.sum(1) / np.maximum(count, 1) for r in ranks]
    da, db = (np.where(valid, r - m[:, None], 0.0) for r, m in zip(ranks, mean))
    cov, var_a, var_b = (da * db).sum(1), (da * da).sum(1), (db * db).sum(1)
    ok = (count >= MIN_VIEWS) & (var_a > 0) & (var_b > 0)
    return np.where(ok, cov / np.sqrt(np.maximum(var_a * var_b, 1e-30)), np.nan)


def at_mirror(samples: ViewSamples, positions: torch.Tensor, normals: torch.Tensor, origins: np.ndarray,
              env: torch.Tensor, to_env: np.ndarray) -> torch.Tensor:
    """(P,) bool: each hit's brightness over its views follows the light about their mirror
    directions (rank correlation at least MIRROR), as a highlight's does and shading's or a
    texture's does not (`origins` (V, 3): every view's camera; `to_env`: as in `mirror_light`)."""
    light = lobe_light(env)
    p, n = positions.detach().cpu().double().numpy(), normals.detach().cpu().double().numpy()
    view = samples.view.numpy()
    mirrored = np.stack([mirror_light(light, p, n, origins[np.clip(view[:, k], 0, None)], to_env)
                         for k in range(view.shape[1])], 1)
    rho = rank_correlation(np.nan_to_num(samples.lum.numpy()), mirrored, view >= 0)
    return torch.as_tensor(np.nan_to_num(rho, nan=-1.0) >= MIRROR)


def metallic_weight(tint: torch.Tensor) -> torch.Tensor:
    """The metallic term's weight for a highlight tint: 1 up to DIELECTRIC, 0 from METAL, 1 for NaN."""
    w = ((METAL - tint) / (METAL - DIELECTRIC)).clamp(0.0, 1.0)
    return torch.where(torch.isnan(tint), torch.ones(()), w)


class WeightGrid:
    """Per-voxel values over a coarse grid, looked up at any point (1 outside the grid and in
    voxels without a value)."""

    def __init__(self, lo: torch.Tensor, size: float, res: int, values: torch.Tensor):
        self.lo, self.size, self.res, self.values = lo, float(size), int(res), values

    @classmethod
    def of_tints(cls, positions: torch.Tensor, tint: torch.Tensor, bounds: torch.Tensor, res: int = GRID):
        """The grid over `bounds` (2, 3), `res` voxels along the longest side, each voxel's value
        the `metallic_weight` of the mean tint (P,) of the hits `positions` (P, 3) inside it that
        gave evidence, where at least MIN_EVIDENCE and MIN_SHARE of them did (else 1)."""
        lo = bounds[0].float()
        size = max(float((bounds[1] - bounds[0]).max()) / res * (1 + 1e-4), 1e-9)
        grid = cls(lo, size, res, torch.ones(res ** 3))
        key, inside = grid._keys(positions.cpu())
        tint = tint.cpu()
        use = inside & ~torch.isnan(tint)
        total = torch.zeros(res ** 3).index_add_(0, key[use], tint.float()[use])
        count = torch.zeros(res ** 3).index_add_(0, key[use], torch.ones(int(use.sum())))
        hits = torch.zeros(res ** 3).index_add_(0, key[inside], torch.ones(int(inside.sum())))
        enough = (count >= MIN_EVIDENCE) & (count >= MIN_SHARE * hits)
        mean = torch.where(enough, total / count.clamp_min(1), torch.full((), float("nan")))
        grid.values = metallic_weight(mean).float()
        return grid

    def _keys(self, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each position's voxel index and whether it lies inside the grid (on the positions' device)."""
        cell = torch.floor((positions.detach().float() - self.lo.to(positions.device)) / self.size).long()
        inside = ((cell >= 0) & (cell < self.res)).all(1)
        cell = cell.clamp(0, self.res - 1)
        return (cell[:, 0] * self.res + cell[:, 1]) * self.res + cell[:, 2], inside

    def __call__(self, positions: torch.Tensor) -> torch.Tensor:
        key, inside = self._keys(positions)
        values = self.values.to(positions.device)
        return torch.where(inside, values[key], torch.ones((), device=positions.device))

    @property
    def full(self) -> bool:
        """Every voxel keeps the whole term."""
        return bool((self.values >= 1.0).all())


class PriorReading:
    """The metallic term's weight over a fit (`grid`: None where the prior stays whole; `decision`:
    fit.json's `decisions.prior`): read from the images' highlights before the first step, with
    the capture's light at once, with a learned light again at READ_AT of the schedule (`due`,
    `read`), keeping only the evidence whose highlights sit about the light's mirror direction."""

    def __init__(self, scene, capture, pool, cfg, known_env: torch.Tensor | None):
        from vq_mitsuba.engine import skips

        self.grid, self.pending, self.read_step = None, False, None
        t, setting = cfg.train, cfg.loss.prior_evidence
        if setting != "auto" or cfg.loss.w_lam <= 0 or cfg.loss.lam_metallic <= 0:
            self.decision = skips.decision(setting, "whole", f"loss.prior_evidence = {setting}" if setting != "auto"
                                           else "no metallic prior to weigh (loss.w_lam or loss.lam_metallic is 0)")
            return
        gen = torch.Generator().manual_seed(skips.np_seed(t.seed, 5))
        pick = torch.randperm(len(pool), generator=gen)[:HITS].to(pool.position.device)
        self.pos, self.nrm = pool.position[pick].cpu(), pool.normal[pick].cpu()
        self.views = sample_views(scene, capture, self.pos, self.nrm, t.alpha_threshold, skips.np_seed(t.seed, 6))
        self.tint = highlight_tint(self.views)
        self.origins = np.array([cam.origin for cam in capture.cameras], np.float64).reshape(-1, 3)
        self.bounds = torch.tensor(np.array(capture.mesh.bounds), dtype=torch.float32)
        self.setting = setting
        # world directions into the lat-long convention of `vq_mitsuba.data.envmaps`
        self.to_env = (BLENDER_ENV_TO_WORLD[:3, :3] @ np.linalg.inv(np.asarray(capture.envmap_to_world)[:3, :3]))
        if known_env is not None:
            self.read(known_env, None)
        else:
            self._weigh(self.tint, None)
            self.pending = self.grid is not None

    def due(self, progress: float) -> bool:
        """The learned light is to be read now."""
        return self.pending and progress >= READ_AT

    def read(self, env: torch.Tensor, step: int | None) -> None:
        """Keep the evidence of the hits whose highlight sits about the mirror direction of the
        light `env` (`at_mirror`) and weigh the prior again (`step`: the step of a learned light)."""
        kept = at_mirror(self.views, self.pos, self.nrm, self.origins, env, self.to_env)
        had = ~torch.isnan(self.tint)
        self.tint = torch.where(kept, self.tint, torch.full((), float("nan")))
        self.pending, self.read_step = False, step
        self._weigh(self.tint, {"hits_at_mirror": int((had & kept).sum()), "hits_not_at_mirror": int((had & ~kept).sum()),
                                "read_at_step": step})

    def _weigh(self, tint: torch.Tensor, mirror: dict | None) -> None:
        from vq_mitsuba import messages
        from vq_mitsuba.engine import skips

        grid = WeightGrid.of_tints(self.pos, tint, self.bounds)
        shown = ~torch.isnan(tint)
        weight = grid(self.pos)
        record = {"hits": len(self.pos), "hits_with_highlight": int(shown.sum()),
                  "tint_median": float(tint[shown].median()) if bool(shown.any()) else None,
                  "share_weakened": float((weight < 1).float().mean()), "share_off": float((weight == 0).float().mean()),
                  "mean_weight": float(weight.mean())}
        seen = (f"{record['hits_with_highlight']} of {len(self.pos)} training hits show a highlight (in {RANK + 1} "
                f"views at least {HIGHLIGHT:g} x their median view's luminance) on a coloured surface")
        if mirror is not None:
            record.update(mirror)
            light = "the capture's light" if mirror["read_at_step"] is None else \
                f"the light learned by step {mirror['read_at_step']}"
            seen += (f" about the mirror direction of {light} ({mirror['hits_not_at_mirror']} bright elsewhere: "
                     "shading or texture, not a highlight)")
        self.grid = None if grid.full else grid
        if grid.full:
            self.decision = {**skips.decision(self.setting, "whole", f"{seen}; no voxel's highlights keep more than "
                                              f"{DIELECTRIC:g} of its colour beyond white light's (median "
                                              + ("none" if record["tint_median"] is None
                                                 else f"{record['tint_median']:.2f}")
                                              + "): the metallic prior is whole"), **record}
            if mirror is not None:
                messages.note(f"prior: {self.decision['reason']}")
            return
        reason = (f"{seen}, their highlights keeping a median {record['tint_median']:.2f} of the surface's colour "
                  f"(0: white light added, as a dielectric's; 1: all of it, as a metal's); the metallic prior is "
                  f"weakened on {100 * record['share_weakened']:.0f} % of the hits "
                  f"(off on {100 * record['share_off']:.0f} %, from a tint of {METAL:g}), mean weight "
                  f"{record['mean_weight']:.2f}")
        messages.note(f"prior: {reason}")
        self.decision = {**skips.decision(self.setting, "weighed", reason), **record}

    def state_dict(self) -> dict:
        return {"pending": self.pending, "read_step": self.read_step, "decision": self.decision,
                "tint": self.tint.clone() if hasattr(self, "tint") else None}

    def load_state_dict(self, state: dict | None) -> None:
        """Resume: a reading of the learned light done before the checkpoint is kept as it was (the
        light it read has moved on since)."""
        if state is None or state["pending"] or state["read_step"] is None or state["tint"] is None:
            return
        self.tint, self.pending, self.read_step = state["tint"].cpu(), False, state["read_step"]
        grid = WeightGrid.of_tints(self.pos, self.tint, self.bounds)
        self.grid, self.decision = None if grid.full else grid, state["decision"]
