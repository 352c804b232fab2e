"""The `neus` config section: geometry reconstruction from posed, masked images."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

from ..errors import InputError


@dataclass
class NeuSConfig:
    seed: int = 0  # network initialisation, ray batches and sample jitter
    iterations: int = 4000  # training steps (schedule: steps or time_limit_s, whichever ends first; on 2 CPU cores with nothing else running, 4000 steps take 314-356 s on the Cycles scenes)
    time_limit_s: float = 600.0  # stop training after this many seconds (0: no limit)
    batch_rays: int = 512  # rays per step, drawn from all views
    n_samples: int = 24  # stratified samples per ray inside its occupied interval
    lr: float = 1e-2  # Adam learning rate of the feature grids and the colour network
    lr_sdf_mlp: float = 1e-3  # Adam learning rate of the SDF MLP (its output is added to the SDF)
    lr_variance: float = 2e-3  # Adam learning rate of the sharpness parameter
    lr_decay: float = 0.1  # learning rate at the end, relative to the start (cosine decay)
    warmup: int = 100  # linear learning-rate warm-up steps
    levels: int = 4  # resolution levels of the dense feature grid
    base_res: int = 16  # coarsest grid resolution (points per axis)
    max_res: int = 64  # finest grid resolution
    features: int = 2  # features per grid level
    hidden: int = 64  # width of the SDF and colour MLPs
    geo_features: int = 15  # SDF-network features passed to the colour network
    reflect: bool = True  # the colour network sees the view direction reflected about the normal and their cosine (as Ref-NeRF, NeRO), not the view direction: a glossy surface's highlights then follow its normal, so a smooth surface explains them; Cycles data, basecolor gap to the true mesh (mean over material seeds): texture 1.45 dB (4 seeds) against 2.41 without (2 seeds), balls 0.87, demo -0.28 (-0.41 without)
    coarse_to_fine: float = 0.3  # fraction of training (steps or time) over which finer grid levels are faded in
    init: str = "hull"  # SDF initialisation: hull (smoothed visual-hull distance) or sphere
    init_radius: float = 0.6  # sphere initialisation radius (normalised box units)
    init_variance: float = 0.5  # initial log-sharpness / 10: s = exp(10 * variance)
    w_eikonal: float = 0.1  # eikonal loss weight
    w_mask: float = 0.1  # mask (BCE on accumulated opacity) loss weight
    hull_resolution: int = 128  # visual hull / occupancy grid resolution
    hull_threshold: float = 0.5  # alpha above which a pixel is foreground for carving
    hull_min_views: float = 0.75  # a voxel must be inside this fraction of the views' frusta
    occupancy_every: int = 500  # steps between occupancy-grid refreshes from the SDF
    march_steps: int = 128  # coarse steps per ray used to find its occupied interval
    mesh_resolution: int = 256  # marching-cubes grid resolution
    min_component: float = 0.05  # drop connected pieces with fewer faces than this fraction of the largest
    keep_largest: bool = False  # keep only the largest connected component
    smooth_iterations: int = 0  # Taubin smoothing steps after marching cubes (0: none)
    normal_smoothing: int = 20  # vertex-normal averaging steps over edge neighbours, positions kept (0: none)
    max_faces: int = 200000  # quadric decimation to this many faces (0: no decimation)
    checkpoint_every: int = 500  # steps between NeuS checkpoints (RUN_DIR/neus.pt)
    threads: int = 1  # torch CPU threads (0: leave torch's default); 1 is fastest on a busy shared CPU




def _help() -> dict[str, str]:
    """Each key's meaning: the comment beside its field above."""
    import inspect
    import re

    out = {}
    for line in inspect.getsource(NeuSConfig).splitlines():
        m = re.match(r"\s+(\w+): \w+ = .*?#\s*(.*)$", line)
        if m:
            out[m.group(1)] = m.group(2)
    return out


def describe() -> list[str]:
    """`neus.key = default  meaning` lines, for --help-config output."""
    meaning = _help()
    return [f"  neus.{f.name} = {getattr(NeuSConfig(), f.name)!r}  {meaning.get(f.name, '')}".rstrip()
            for f in fields(NeuSConfig)]


def _parse(value: str, typ):
    if typ is bool:
        low = value.strip().lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ValueError(value)
    return typ(value)


def apply_overrides(cfg: NeuSConfig, overrides: list[str] | None) -> NeuSConfig:
    """A copy of cfg with `neus.key=value` (or `key=value`) overrides applied; bad ones are InputErrors."""
    cfg = dataclasses.replace(cfg)
    types = {f.name: type(getattr(cfg, f.name)) for f in fields(cfg)}
    for item in overrides or []:
        if "=" not in item:
            raise InputError(None, f"bad override '{item}': expected neus.KEY=VALUE")
        key, value = item.split("=", 1)
        key = key.strip()
        if key.startswith("neus."):
            key = key[5:]
        if key not in types:
            raise InputError(None, f"unknown config key 'neus.{key}' (known: {', '.join(sorted(types))})")
        try:
            setattr(cfg, key, _parse(value, types[key]))
        except ValueError:
            raise InputError(None, f"bad value for neus.{key}: {value!r} (expected {types[key].__name__})") from None
    validate(cfg)
    return cfg


def from_dict(data: dict | None) -> NeuSConfig:
    """NeuSConfig from a mapping (e.g. the `neus` section of a YAML file)."""
    return apply_overrides(NeuSConfig(), [f"{k}={v}" for k, v in (data or {}).items()])


def validate(cfg: NeuSConfig) -> None:
    if cfg.init not in ("hull", "sphere"):
        raise InputError(None, f"neus.init must be 'hull' or 'sphere', got {cfg.init!r}")
    for key in ("iterations", "batch_rays", "n_samples", "levels", "base_res", "max_res", "features", "hidden",
                "hull_resolution", "march_steps", "mesh_resolution"):
        if getattr(cfg, key) < 1:
            raise InputError(None, f"neus.{key} must be positive")
    for key in ("smooth_iterations", "normal_smoothing", "max_faces"):
        if getattr(cfg, key) < 0:
            raise InputError(None, f"neus.{key} must be >= 0")
    if cfg.base_res < 2 or cfg.max_res < cfg.base_res:
        raise InputError(None, "neus.base_res must be >= 2 and neus.max_res >= neus.base_res")
