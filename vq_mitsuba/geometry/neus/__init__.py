"""NeuS on the process's device (`backend.torch_device()`: a CPU or a GPU): geometry (an SDF) and
appearance from posed images, with alpha masks or without.

Model (NeuS, Wang et al. 2021; VQ-NeRF supplement Eq. 1-2): an SDF network f and a colour network
c; along a ray, section i between samples has opacity
    alpha_i = max((Phi_s(f_i - cos * d_i / 2) - Phi_s(f_i + cos * d_i / 2)) / Phi_s(f_i - cos * d_i / 2), 0)
with Phi_s the logistic sigmoid of learned sharpness s, and the pixel colour is the
alpha-composited c. Losses: L1 colour, eikonal (|grad f| = 1), BCE between accumulated opacity
and the alpha mask (with masks; without them a background model takes the rest of each ray).

On a GPU the model, its training rays and its grids live on the GPU (the grid lookup runs in torch
there), and a step reads its losses back every 10 steps only. What makes it fast
enough for two CPU cores:
- the SDF network is a tiny MLP fed by a multi-resolution feature grid (dense levels, hashed past
  2^neus.hash_log2 points), with finer levels faded in coarse-to-fine; its SDF gradient is
  computed in closed form, so the eikonal loss back-propagates without a second derivative; on the
  CPU one compiled kernel looks the grid up with its Jacobian and adds its table gradient;
- a long stage's step runs under `torch.compile` in a fixed-shape form (`NeuS.training_step`);
- the masks give a visual hull; the object lives in the hull's bounding box (normalised to
  [-1, 1]^3), the SDF starts as the hull's smoothed signed distance (or a sphere), and samples are
  only placed where the ray crosses the occupancy grid: from its entry into the (dilated) hull to
  just past the first cell the current SDF marks as deep inside (refreshed during training);
- every ray batch is drawn from the foreground-dilated pixels of all views.

Without masks (`neus.background`: model, or auto on a capture without alpha or masks), as NeuS
trains DTU "w/o mask": the object lives in a bounding sphere framed from the cameras (and the
sparse points of a COLMAP model, or an IDR capture's scale_mat_0), which is the normalised box's
unit sphere and takes the hull's place (occupancy, SDF crop); the SDF starts as a sphere; rays come
from every pixel; behind the foreground each ray composites a NeRF++ background (density and colour
of points outside the sphere from their inverted-sphere coordinates (x/r, 1/r) and the view
direction); the colour loss is on every pixel and there is no mask loss. The exported mesh keeps
the largest piece inside the sphere, without a supporting plane (`support_plane`).

The rooms: `framing` (where the object is without masks), `hull` (the visual hull), `networks` (the
grid and the networks; `grid_kernel` its CPU lookup), `renderer` (the model: its box, occupancy and
volume rendering of rays; it takes rays, not a capture), `rays` (a capture's box, training rays and
camera renders: `neus_for` builds the model), `mesh_export` (the surface as a mesh) and `training`
(the training loop and `reconstruct`) and `method` (NeuS as the geometry method "neus" of
`vq_mitsuba.geometry.methods`: its framing, sparse points and scores; the stage around it is
`vq_mitsuba.geometry.stage`).

The names below are imported from their rooms when first asked for, so that importing `method` (to
register NeuS) loads no training code.
"""

import importlib

CHECKPOINT = "neus.pt"  # NeuS's checkpoint in a run: `--resume` of the geometry stage continues from it

# each public name and the room that defines it
_ROOMS = {
    "networks": ("COARSE_GRID", "FINE_GRID", "FINE_GRID_FROM_PX", "HASH_PRIMES", "MASKED_GRID", "BackgroundNetwork",
                 "ColorNetwork", "DenseGrid", "NeuSModel", "SDFNetwork", "trilinear"),
    "training": ("NeuSTraining", "NeuSResult", "check_architecture", "rate_spread", "reconstruct", "train"),
    "framing": ("bounding_sphere", "box_footprint_px", "support_from_points", "uses_background_model", "well_seen"),
    "hull": ("hull_box", "carve", "hull_sdf"),
    "mesh_export": ("extract_mesh",),
    "rays": ("choose_grid", "neus_for", "render_view"),
    "renderer": ("Box", "NeuS", "TrainingRays", "encode_srgb"),
    "method": ("NeuSMethod",),
}
_ROOM_OF = {name: room for room, names in _ROOMS.items() for name in names}
__all__ = list(_ROOM_OF)


def __getattr__(name: str):
    room = _ROOM_OF.get(name)
    if room is None:  # a room itself (`from vq_mitsuba.geometry.neus import training`) is imported by Python
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{room}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
