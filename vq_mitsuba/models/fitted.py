"""A fitted scene as the layers above the trainer see it: networks, lighting and geometry."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch

from vq_mitsuba.brdf import select
from vq_mitsuba.config import Config
from vq_mitsuba.models.material_edits import Edit, apply_edits
from vq_mitsuba.models.fields import ContinuousMaterial
from vq_mitsuba.models.residual import ResidualField
from vq_mitsuba.models.vq import DiscreteBranch

if TYPE_CHECKING:
    import trimesh


@dataclass
class FittedLamps:
    """Point lamps fitted beside the envmap: positions (K, 3) in the run's world or, `in_camera`, in
    the frame of the camera that sees the scene (a flash; Mitsuba camera space), and RGB radiant
    intensities (K, 3)."""

    position: np.ndarray
    intensity: np.ndarray
    in_camera: bool = False

    def light(self, camera_to_world: np.ndarray, scale: float, device) -> Callable:
        """The lamps as a shading scene's `lamps` (`render.shading.ShadingScene`) for a view whose
        camera is `camera_to_world` (4, 4), their intensities times `scale`."""
        position = np.asarray(self.position, dtype=np.float64)
        if self.in_camera:
            position = position @ np.asarray(camera_to_world)[:3, :3].T + np.asarray(camera_to_world)[:3, 3]
        p = torch.as_tensor(position, dtype=torch.float32, device=device)
        i = torch.as_tensor(np.asarray(self.intensity) * scale, dtype=torch.float32, device=device)
        return lambda views=None: (p, i)


@dataclass
class FittedModel:
    cfg: Config
    model: ContinuousMaterial  # the continuous branch (encoder + decoders), eval mode
    discrete: DiscreteBranch | None  # the discrete branch, None when the run has none (or it never started)
    envmap: np.ndarray  # (H, W, 3) linear radiance, lat-long in Mitsuba's frame
    envmap_to_world: np.ndarray  # (4, 4) the envmap's frame in the run's world
    world: str  # "mitsuba" (Y up) or "blender" (Z up): the world convention of the run's capture
    mesh: trimesh.Trimesh
    step: int  # training steps behind this state (-1 when the state file does not say)
    edits: list[Edit] = field(default_factory=list)  # material edits, applied wherever the fields are read
    # The view-dependent residual of novel views under the capture's own light (None: the run has
    # none); renders under other light, of edits and exports leave it out (`render.views.Renderer`).
    residual: ResidualField | None = None
    # Point lamps fitted beside the envmap (None: the envmap alone); renders under the run's own
    # light include them, relit ones leave them out.
    lamps: FittedLamps | None = None

    @torch.no_grad()
    def materials_at(self, points: torch.Tensor, discrete: bool = False, ids: bool = True) -> dict[str, torch.Tensor]:
        """The BRDF at world points (N, 3), with the run's edits applied: basecolor (N, 3) linear,
        metallic (N,), roughness (N,) of the continuous branch; with a discrete branch also
        `material` (N,), the ranked material id 1..M. `discrete=True` adds `discrete`, the same
        three maps decoded from each point's material (edited alike). `ids=False` skips the
        material ids where no edit needs them (the cheaper bounce evaluation)."""
        out = self.model(points)
        brdf = select(out)
        material, od = None, None
        if self.discrete is not None and (discrete or ids or self.edits):
            od = self.discrete(out["z"], n_codes=self.num_materials)
            material = od["index"] + 1
        r0 = self.cfg.field.roughness_min
        if self.edits:
            brdf = apply_edits(self.edits, points, brdf, material, r0)
        if material is not None:
            brdf["material"] = material
        if discrete and od is not None:
            d = select(od)
            brdf["discrete"] = apply_edits(self.edits, points, d, material, r0) if self.edits else d
        return brdf

    @property
    def num_materials(self) -> int | None:
        """M, the chosen number of materials, or None without a discrete branch."""
        return int(self.discrete.num_materials) if self.discrete is not None else None


def material_networks(cfg: Config, mesh, device) -> tuple[ContinuousMaterial, DiscreteBranch | None]:
    """The continuous branch over the mesh's bounding box and, with vq.enabled, the discrete
    branch: what a fit trains and what a finished run's checkpoint is loaded into."""
    bbox = torch.tensor(np.asarray(mesh.bounds), dtype=torch.float32)
    model = ContinuousMaterial(cfg.field, bbox[0], bbox[1]).to(device)
    discrete = DiscreteBranch(cfg.field, cfg.vq.num_codes, cfg.vq.decay, cfg.vq.commitment).to(device) \
        if cfg.vq.enabled else None
    return model, discrete
