"""Typed configuration: one dataclass per component; YAML presets and `--set key=value` overrides.

Every field's comment is its documentation (`vq-mitsuba fit --help-config` prints them).
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from pathlib import Path

import yaml

from vq_mitsuba.errors import InputError


@dataclass
class FieldConfig:
    """The material field: encoder MLP with positional encoding, latent z, BRDF decoders."""

    pe_freqs: int = 8  # positional-encoding frequencies of the surface point
    hidden: int = 64  # width of the encoder's 7 FC layers
    latent: int = 16  # dimension of the latent z
    decoder_hidden: int = 64  # width of each decoder MLP (3 FC layers with a skip)
    roughness_min: float = 0.02  # lower end of the roughness output range [roughness_min, 1]
    pe_anneal: float = 0.5  # share of training over which the encoding frequencies open (0: all at once)
    metallic_init: float = 0.02  # metallic output at initialisation (0: PyTorch's default, about 0.5)


@dataclass
class EnvmapConfig:
    """The learned lat-long environment map (used only when the capture's lighting is unknown)."""

    height: int = 128  # rows of the learned envmap at the end of the fit (width is twice this); it grows from 32
    init_scale: float = 2.0  # initial radiance as a multiple of the mean foreground pixel value
    lr: float = 0.02  # Adam learning rate of the log-radiance texels
    tv_weight: float = 1e-4  # weight of the smoothness term on neighbouring log-radiance texels


@dataclass
class LossConfig:
    """Loss weights of both branches (the paper's w1..w6)."""

    w_rec_c: float = 0.2  # w1: L2 reconstruction of the continuous branch
    w_rec_d: float = 1.0  # w2: L2 reconstruction of the discrete branch
    w_chr: float = 1.0  # w3: chromaticity of the discrete against the continuous basecolor
    w_vq: float = 1.0  # w4: VQ (commitment) loss
    w_lam: float = 1e-4  # w5: Lambertian prior (metallic towards 0, roughness towards 1)
    lam_metallic: float = 2.0  # weight of the Lambertian prior's metallic term relative to its roughness term
    lam_decay: float = 0.1  # w5 at the end of training relative to its start (1: constant)
    metallic_barrier_until: float = 0.3  # training share in (0, 1] during which the metallic prior is -log(1 - metallic)
    w_sm: float = 0.0  # w6: colour-aware smoothness of neighbouring pixels (0: off)
    sm_alpha: float = 60.0  # alpha of L_sm: how fast image differences switch the smoothness off
    sm_beta: float = 0.1  # beta of L_sm: weight of metallic/roughness differences
    gamma: float = 2.2  # reconstruction compares x^(1/gamma)


@dataclass
class VQConfig:
    """The discrete branch: codebook, codeword dropout and the choice of the material count M."""

    enabled: bool = True  # train the discrete branch and rank its codewords (false: continuous branch only)
    num_codes: int = 8  # M0: codebook size
    warmup_frac: float = 0.3  # share of training before the codebook starts (from k-means of the latents)
    decay: float = 0.99  # EMA decay of the codebook updates
    commitment: float = 0.1  # lambda of the VQ loss (Eq. 8)
    dropout_max: float = 0.7  # codeword dropout rate of the last codeword (rates rise linearly to it)
    protected: int = 1  # first codewords that are never dropped
    rank_eps: float = 0.002  # epsilon of the err_k rule that chooses M
    rank_pixels: int = 4096  # training pixels on which err_k is measured
    min_share: float = 0.005  # codewords chosen by fewer pixels than this share are not materials
    merge_tol: float = 0.1  # codewords decoding within this BRDF distance of a higher-ranked one are duplicates (0: off)
    joint_scale: float = 0.05  # share in (0, 1] of the discrete branch's gradient that reaches the shared encoder
    lam_decay: float = 0.1  # Lambertian prior decay on the discrete branch (1: constant)


@dataclass
class AblationConfig:
    """Switches of the paper's ablations; each preset configs/ablation_*.yaml sets one."""

    no_ranking: bool = False  # M = vq.num_codes, no dropout ranking
    separate: bool = False  # the discrete branch's gradients do not reach the encoder
    single_branch: bool = False  # after the warm-up, train the discrete branch alone
    shared_light: bool = False  # the discrete loss also trains the envmap and the bounce light
    single_pass_ranking: bool = False  # the paper's single ranking pass (no moving of redundant codewords)


@dataclass
class TrainConfig:
    """The training loop."""

    iterations: int = 3000  # optimisation steps
    batch_rays: int = 2048  # random foreground pixels per step, drawn across all training views
    spp: int = 8  # emitter + BSDF sample pairs per pixel and step
    lr: float = 2e-3  # Adam learning rate of the material networks
    lr_decay: float = 0.1  # learning-rate factor reached at the last iteration (exponential decay)
    seed: int = 0  # seed of the networks, batches and light samples
    checkpoint_every: int = 500  # steps between checkpoints
    log_every: int = 50  # steps between loss-curve entries
    alpha_threshold: float = 0.99  # pixels with alpha below this are not fitted
    pixel_jitter: int = 4  # primary hits traced per pixel, stratified (a square number; 0: pixel centre)
    bounces: int = 1  # interreflections simulated (0: direct light only)
    bounce_after: int = 300  # steps of direct light only before the bounce is simulated
    time_limit_s: float = 0.0  # stop after this many seconds (0: no limit)
    snapshot_s: str = ""  # comma-separated fit seconds at which a copy of the state is kept in snapshots/


@dataclass
class RenderConfig:
    """Rendering views of a fitted run."""

    spp: int = 256  # samples per pixel (primary rays x light samples)
    aa: int = 16  # primary rays per pixel, stratified (a square number)
    chunk: int = 65536  # surface points shaded per Mitsuba call


@dataclass
class NeuSConfig:
    """The geometry stage: NeuS on posed, masked images, then mesh export."""

    seed: int = 0  # seed of the networks, ray batches and sample jitter
    iterations: int = 4000  # training steps
    time_limit_s: float = 600.0  # stop training after this many seconds (0: no limit)
    batch_rays: int = 512  # rays per step, drawn from all views
    n_samples: int = 24  # stratified samples per ray inside its occupied interval
    lr: float = 1e-2  # Adam learning rate of the feature grids and the colour network
    lr_sdf_mlp: float = 1e-3  # Adam learning rate of the SDF MLP
    lr_variance: float = 2e-3  # Adam learning rate of the sharpness parameter
    lr_decay: float = 0.1  # learning rate at the end relative to the start (cosine decay)
    warmup: int = 100  # steps of linear learning-rate warm-up
    levels: int = 4  # resolution levels of the dense feature grid
    base_res: int = 16  # coarsest grid resolution (points per axis)
    max_res: int = 64  # finest grid resolution
    features: int = 2  # features per grid level
    hidden: int = 64  # width of the SDF and colour MLPs
    geo_features: int = 15  # SDF-network features passed to the colour network
    reflect: bool = True  # the colour network sees the reflected view direction instead of the view direction
    coarse_to_fine: float = 0.3  # share of training over which finer grid levels fade in
    init: str = "hull"  # SDF initialisation: hull (smoothed visual-hull distance) or sphere
    init_radius: float = 0.6  # radius of the sphere initialisation (normalised box units)
    init_variance: float = 0.5  # initial log-sharpness / 10 (s = exp(10 * variance))
    w_eikonal: float = 0.1  # eikonal loss weight
    w_mask: float = 0.1  # mask loss weight (BCE on the accumulated opacity)
    hull_resolution: int = 128  # visual-hull / occupancy grid resolution
    hull_threshold: float = 0.5  # alpha above which a pixel is foreground for carving
    hull_min_views: float = 0.75  # share of the views whose frusta must hold a voxel for it to be carved in
    occupancy_every: int = 500  # steps between occupancy-grid refreshes from the SDF
    march_steps: int = 128  # coarse steps per ray that find its occupied interval
    mesh_resolution: int = 256  # marching-cubes grid resolution
    min_component: float = 0.05  # connected pieces smaller than this share of the largest are dropped
    keep_largest: bool = False  # keep only the largest connected component
    smooth_iterations: int = 0  # Taubin smoothing steps after marching cubes
    normal_smoothing: int = 40  # vertex-normal averaging steps over edge neighbours (positions kept)
    normal_smoothing_angle: float = 15.0  # neighbours whose normals differ by more (degrees) are not averaged
    max_faces: int = 200000  # quadric decimation to this many faces (0: none)
    checkpoint_every: int = 500  # steps between NeuS checkpoints
    threads: int = 1  # torch CPU threads for NeuS (0: torch's default)


@dataclass
class CaptureConfig:
    """How a capture's images are read: their size, the mask, the views kept out of training."""

    downscale: int = 1  # divide the image width and height by this, averaging blocks of pixels
    background_color: str = ""  # R,G,B (sRGB, 0..1) of a plain backdrop, keyed out as the mask ("": none)
    background_tolerance: float = 0.08  # sRGB distance from background_color still counted as backdrop
    holdout: int = 0  # keep every K-th view out of training, for `eval` to score (0: none)


@dataclass
class TexelConfig:
    """The per-texel baseline (`vq_mitsuba.eval.texel`): principled textures on a UV atlas."""

    resolution: int = 256  # texels per side of each material texture
    uv_padding: int = 2  # texels between charts in the UV atlas
    envmap_height: int = 32  # rows of the learned lat-long envmap (width is twice this)
    env_init_scale: float = 2.0  # initial radiance as a multiple of the mean foreground pixel value
    spp: int = 16  # samples per pixel of each training render
    max_depth: int = 3  # path length of the integrator (3: direct light plus one bounce)
    views_per_step: int = 1  # random whole training views rendered per Adam step
    lr_texture: float = 0.05  # Adam learning rate of the texels
    lr_envmap: float = 0.03  # Adam learning rate of the envmap's log radiance
    lr_decay: float = 0.1  # learning-rate factor reached at the time limit
    gamma: float = 2.2  # the loss compares x^(1/gamma)
    tv_weight: float = 1.0  # weight of the mean squared difference of neighbouring texels
    env_tv_weight: float = 1e-4  # weight of the smoothness of the envmap's log radiance
    init_basecolor: float = 0.5  # initial basecolor texels
    init_metallic: float = 0.1  # initial metallic texels
    init_roughness: float = 0.5  # initial roughness texels
    roughness_min: float = 0.02  # roughness texels are clamped to [roughness_min, 1]
    iterations: int = 0  # stop after this many steps (0: only the time limit)
    seed: int = 0  # seed of the view order and the Monte Carlo samples


@dataclass
class Config:
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    envmap: EnvmapConfig = dataclasses.field(default_factory=EnvmapConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    vq: VQConfig = dataclasses.field(default_factory=VQConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    neus: NeuSConfig = dataclasses.field(default_factory=NeuSConfig)
    ablation: AblationConfig = dataclasses.field(default_factory=AblationConfig)
    texel: TexelConfig = dataclasses.field(default_factory=TexelConfig)
    capture: CaptureConfig = dataclasses.field(default_factory=CaptureConfig)


PRESETS_DIR = Path(__file__).resolve().parent.parent / "configs"


def presets() -> list[str]:
    """Names of the presets in configs/."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def preset_path(name: str) -> Path:
    """configs/NAME.yaml; an InputError listing the presets when there is none of that name."""
    path = PRESETS_DIR / f"{name}.yaml"
    if not path.is_file():
        raise InputError(None, f"unknown preset '{name}' (presets: {', '.join(presets())})")
    return path


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def _coerce(value, typ, key: str, source):
    if typ is bool:
        if isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise InputError(source, f"'{key}' expects true/false, got '{value}'")
        return bool(value)
    try:
        if typ is int and isinstance(value, float) and not value.is_integer():
            raise ValueError
        out = typ(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(source, f"'{key}' expects {typ.__name__}, got '{value}'") from None
    if typ is float and not math.isfinite(out):
        raise InputError(source, f"'{key}' must be a finite number, got {value}")
    return out


def _apply(cfg, data: dict, source, prefix: str = "") -> None:
    hints = typing.get_type_hints(type(cfg))
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in hints:
            known = ", ".join(hints)
            raise InputError(source, f"unknown config key '{name}' (known here: {known})")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError(source, f"'{name}' is a section; expected a mapping")
            _apply(current, value, source, name + ".")
        else:
            setattr(cfg, key, _coerce(value, hints[key], name, source))


def read_config_file(path: str | Path) -> dict:
    """A YAML config file as a mapping of sections; InputError naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise InputError(path, f"invalid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a mapping of sections")
    return data


# Value ranges of numeric keys. Every other numeric key must be >= 0 (weights, seeds, time limits,
# counts that may be zero); a key named in none of these tables and in ANY_SIGN may be negative.
POSITIVE = {
    "field.pe_freqs", "field.hidden", "field.latent", "field.decoder_hidden", "envmap.height", "envmap.init_scale",
    "envmap.lr", "loss.gamma", "vq.num_codes", "vq.rank_pixels", "train.iterations", "train.batch_rays", "train.spp",
    "train.lr", "train.lr_decay", "train.checkpoint_every", "train.log_every", "render.spp", "render.aa",
    "render.chunk", "neus.lr", "neus.lr_sdf_mlp", "neus.lr_variance", "neus.lr_decay", "neus.init_radius",
    "texel.resolution", "texel.envmap_height",
    "texel.env_init_scale", "texel.spp", "texel.max_depth", "texel.views_per_step", "texel.lr_texture",
    "texel.lr_envmap", "texel.lr_decay", "texel.gamma", "capture.downscale",
}
UNIT_INTERVAL = {
    "field.roughness_min", "field.pe_anneal", "vq.warmup_frac", "vq.decay", "vq.dropout_max", "vq.min_share",
    "train.alpha_threshold", "train.lr_decay", "neus.lr_decay", "neus.hull_threshold", "neus.hull_min_views",
    "neus.coarse_to_fine", "neus.min_component", "texel.lr_decay", "texel.init_basecolor", "texel.init_metallic",
    "texel.init_roughness", "texel.roughness_min", "capture.background_tolerance",
}
ANY_SIGN = {"neus.init_variance"}
SQUARE = {"train.pixel_jitter": "0: pixel centre", "render.aa": "primary rays per pixel on a grid"}


def _numeric_keys(cfg, prefix: str = ""):
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numeric_keys(value, f"{prefix}{f.name}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            yield f"{prefix}{f.name}", value


def _check_ranges(cfg: Config, source) -> None:
    """Values that parse but make no sense; `source` is the layer that set them (file or --set)."""
    def fail(message: str):
        raise InputError(source, message)

    for key, value in _numeric_keys(cfg):
        if key in POSITIVE and not value > 0:
            fail(f"{key} must be > 0, got {value}")
        if key in UNIT_INTERVAL and not 0.0 <= value <= 1.0:
            fail(f"{key} must be in [0, 1], got {value}")
        if key not in ANY_SIGN and value < 0:
            fail(f"{key} must be >= 0, got {value}")
        if key in SQUARE and value > 0 and round(value ** 0.5) ** 2 != value:
            fail(f"{key} must be a square number ({SQUARE[key]}), got {value}")
    if cfg.field.roughness_min >= 1.0:
        fail(f"field.roughness_min must be below 1, got {cfg.field.roughness_min}")

    if not 0.0 <= cfg.field.metallic_init < 1.0:
        fail(f"field.metallic_init must be in [0, 1) (0: default initialisation), got {cfg.field.metallic_init}")
    for key, value, one in (("loss.lam_decay", cfg.loss.lam_decay, "a constant Lambertian prior"),
                            ("vq.lam_decay", cfg.vq.lam_decay, "a constant Lambertian prior"),
                            ("vq.joint_scale", cfg.vq.joint_scale, "the full joint gradient"),
                            ("loss.metallic_barrier_until", cfg.loss.metallic_barrier_until, "the whole fit")):
        if not 0.0 < value <= 1.0:
            fail(f"{key} must be in (0, 1] (1: {one}), got {value}")
    if cfg.train.bounce_after < 0:
        fail(f"train.bounce_after must be >= 0 steps (0: bounces from the first step), got {cfg.train.bounce_after}")
    if cfg.vq.num_codes < 1:
        fail(f"vq.num_codes must be >= 1, got {cfg.vq.num_codes}")
    check_neus(cfg.neus, source)
    if cfg.capture.background_color:
        background_rgb(cfg.capture, source)


def background_rgb(c: CaptureConfig, source=None) -> tuple[float, float, float] | None:
    """capture.background_color as three sRGB values in [0, 1], or None when not set."""
    if not c.background_color.strip():
        return None
    try:
        rgb = tuple(float(v) for v in c.background_color.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise InputError(source, f"capture.background_color must be R,G,B with values in 0..1, got "
                                 f"'{c.background_color}'")
    return rgb


def check_neus(n: NeuSConfig, source=None) -> None:
    """The `neus` section's value ranges."""
    if n.init not in ("hull", "sphere"):
        raise InputError(source, f"neus.init must be 'hull' or 'sphere', got {n.init!r}")
    for key in ("iterations", "batch_rays", "n_samples", "levels", "base_res", "max_res", "features", "hidden",
                "hull_resolution", "march_steps", "mesh_resolution"):
        if getattr(n, key) < 1:
            raise InputError(source, f"neus.{key} must be positive, got {getattr(n, key)}")
    for key in ("smooth_iterations", "normal_smoothing", "max_faces"):
        if getattr(n, key) < 0:
            raise InputError(source, f"neus.{key} must be >= 0, got {getattr(n, key)}")
    if n.base_res < 2 or n.max_res < n.base_res:
        raise InputError(source, "neus.base_res must be >= 2 and neus.max_res >= neus.base_res")


def parse_overrides(overrides: list[str] | None) -> dict:
    """`section.key=value` items (values parsed as YAML) as a nested mapping."""
    nested: dict = {}
    for item in overrides or []:
        if "=" not in item:
            raise InputError(None, f"--set expects key=value, got '{item}'")
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        cur = nested
        for part in parts[:-1]:
            cur = cur.setdefault(part, {})
            if not isinstance(cur, dict):
                raise InputError(None, f"--set {key}: '{part}' is a key, not a section")
        cur[parts[-1]] = yaml.safe_load(value)
    return nested


def load_config(path: str | Path | None = None, overrides: list[str] | None = None, base: dict | None = None,
                preset: str | None = None) -> Config:
    """Defaults <- `base` (a run's saved config) <- preset configs/PRESET.yaml <- YAML file <- `key=value`
    overrides; each layer is checked as it is applied, and an error names the layer."""
    cfg = Config()
    layers: list[tuple[object, dict]] = []
    if base:
        layers.append(("config.yaml", base))
    if preset is not None:
        path_p = preset_path(preset)
        layers.append((path_p, read_config_file(path_p)))
    if path is not None:
        layers.append((path, read_config_file(path)))
    if overrides:
        layers.append(("--set", parse_overrides(overrides)))
    for source, data in layers:
        _apply(cfg, data, source)
        _check_ranges(cfg, source)
    return cfg


def save_config(cfg: Config, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))


def _comments(cls) -> dict[str, str]:
    """Each field's one-line description: the comment beside it in the class body."""
    import inspect
    import re

    out = {}
    for line in inspect.getsource(cls).splitlines():
        m = re.match(r"\s+(\w+): [\w\[\], |]+ = .*?#\s*(.*)$", line)
        if m:
            out[m.group(1)] = m.group(2)
    return out


def describe(cfg_cls=Config, prefix: str = "") -> list[str]:
    """One line per key, `section.key = default: meaning`, for --help-config."""
    lines = []
    comments = _comments(cfg_cls)
    for f in dataclasses.fields(cfg_cls):
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            doc = (type(default).__doc__ or "").strip().splitlines()[0]
            lines.append(f"{prefix}{f.name}: {doc}")
            lines += describe(type(default), prefix + f.name + ".")
        else:
            lines.append(f"  {prefix}{f.name} = {default!r}: {comments.get(f.name, '')}")
    return lines


def markdown() -> str:
    """docs/configuration.md: every key, generated from this module (`python -m vq_mitsuba.config`)."""
    lines = ["# Configuration", "",
             "Generated by `python -m vq_mitsuba.config > docs/configuration.md` from `vq_mitsuba/config.py`; "
             "`vq-mitsuba fit --help-config` prints the same. A run's config is the defaults, then "
             "`--preset NAME` (`configs/NAME.yaml`), then `--config FILE`, then each `--set section.key=value`.",
             ""]
    for f in dataclasses.fields(Config):
        section = f.default_factory()
        lines += [f"## `{f.name}`: {(type(section).__doc__ or '').strip()}", "", "| key | default | meaning |",
                  "|---|---|---|"]
        comments = _comments(type(section))
        for g in dataclasses.fields(section):
            lines.append(f"| `{f.name}.{g.name}` | `{getattr(section, g.name)!r}` | {comments.get(g.name, '')} |")
        lines.append("")
    lines += ["## Presets", ""] + [f"- `{name}`: " + (preset_path(name).read_text().splitlines()[0].lstrip("# ")
                                                       if preset_path(name).read_text().startswith("#") else "")
                                   for name in presets()]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
