"""Typed configuration: one dataclass per component; YAML presets and `--set key=value` overrides.

Each key is declared with `setting(default, help, range)`: the help (one line, what the key does)
and the range live in the field's metadata, where the one validator (`check`), `describe()`
(`vq-mitsuba fit --help-config`) and `markdown()` (docs/configuration.md) read them.

Ranges, a small vocabulary (RANGES):

    ">0"         a number above 0
    ">=0"        a number not below 0 (the default for numbers)
    "[0,1]"      0 <= x <= 1
    "(0,1]"      0 < x <= 1 (learning rates: Adam steps by about lr, so above 1 a fit only diverges)
    "[0,1)"      0 <= x < 1
    ">=2"        a number not below 2
    "[2,1024]"   2 <= x <= 1024 (a marching-cubes grid: its volume is res^3 floats)
    "[0,2]"      0, 1 or 2 (an integer)
    "any"        any finite number (numbers), any text (strings: the default; parsed where used)
    "square"     a square number or 0 (0, 1, 4, 9, ...)
    "square>0"   a square number above 0 (1, 4, 9, ...)
    ("a", "b")   a string that is one of these choices
    None         booleans (true/false)

Every integer lies within +-MAX_INT (booleans are not integers: `iterations: true` is refused), and
every float is finite. A few checks span keys (neus.base_res / neus.max_res, capture.background_color's R,G,B): they are
in `check` too. A saved config.yaml starts with `version:` (CONFIG_VERSION); `upgrade` brings an
older mapping to the current names.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import math
import typing
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import yaml

from vq_mitsuba.errors import InputError

# The range vocabulary: token -> (test of a value, how an error message and the docs say it).
RANGES: dict[str, tuple[typing.Callable[[float], bool], str]] = {
    ">0": (lambda v: v > 0, "> 0"),
    ">=0": (lambda v: v >= 0, ">= 0"),
    ">1": (lambda v: v > 1, "> 1"),
    "[0,1]": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "-1|[0,1]": (lambda v: v == -1 or 0 <= v <= 1, "-1 or in [0, 1]"),
    "(0,1]": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "[0,1)": (lambda v: 0 <= v < 1, "in [0, 1)"),
    ">=2": (lambda v: v >= 2, ">= 2"),
    "[2,1024]": (lambda v: 2 <= v <= 1024, "in [2, 1024]"),
    "[0,2]": (lambda v: 0 <= v <= 2, "0, 1 or 2"),
    "any": (lambda v: True, "any number"),
    "square": (lambda v: v >= 0 and round(v ** 0.5) ** 2 == v, "a square number or 0"),
    "square>0": (lambda v: v > 0 and round(v ** 0.5) ** 2 == v, "a square number > 0"),
}


MAX_INT = 2 ** 31 - 1  # the largest integer a key takes (steps, sizes, seeds: int32 everywhere they go)


def _default_range(default):
    if isinstance(default, bool):
        return None
    if isinstance(default, str):
        return "any"
    return ">=0"


def _range_error(default, range_) -> str | None:
    """Why `range_` does not fit a key whose default is `default` (None when it does)."""
    if isinstance(default, bool):
        return None if range_ is None else "booleans take no range"
    if isinstance(default, str):
        if range_ == "any":
            return None
        if isinstance(range_, tuple) and range_ and all(isinstance(c, str) for c in range_):
            return None if default in range_ else f"default {default!r} is not one of {range_}"
        return "strings take 'any' or a tuple of choices"
    if isinstance(default, (int, float)):
        if range_ not in RANGES:
            return f"unknown range {range_!r} (known: {', '.join(RANGES)})"
        if range_.startswith("square") and not isinstance(default, int):
            return "square ranges are for integers"
        return None
    return f"no range vocabulary for {type(default).__name__}"


def setting(default, help: str, range=dataclasses.MISSING):
    """A config key: `dataclasses.field` with its one-line help and its range in the metadata.

    `range` is a RANGES token, a tuple of string choices, or None (booleans); left out, numbers are
    ">=0", strings "any" and booleans None."""
    if range is dataclasses.MISSING:
        range = _default_range(default)
    problem = _range_error(default, range)
    if problem or not help.strip() or "\n" in help:
        raise ValueError(f"setting({default!r}, {help!r}, {range!r}): {problem or 'help must be one line'}")
    metadata = {"help": help, "range": range}
    if isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass
class FieldConfig:
    """The material field: encoder MLP with positional encoding, latent z, BRDF decoders."""

    pe_freqs: int = setting(8, "positional-encoding frequencies of the surface point", ">0")
    hidden: int = setting(64, "width of the encoder's 7 FC layers", ">0")
    latent: int = setting(16, "dimension of the latent z", ">0")
    decoder_hidden: int = setting(64, "width of each decoder MLP (3 FC layers with a skip)", ">0")
    roughness_min: float = setting(0.02, "lower end of the roughness output range [roughness_min, 1]", "[0,1)")
    pe_anneal: float = setting(0.5, "share of training over which the encoding frequencies open (0: all at once)",
                                    "[0,1]")
    metallic_init: float = setting(0.02, "metallic output at initialisation (0: PyTorch's default, about 0.5)", "[0,1)")


@dataclass
class EnvmapConfig:
    """The learned lat-long environment map (used only when the capture's lighting is unknown)."""

    height: int = setting(
        128, "rows of the learned envmap at the end of the fit (width is twice this); it grows from 32", ">=2")
    init_scale: float = setting(2.0, "initial radiance as a multiple of the mean foreground pixel value", ">0")
    lr: float = setting(0.05, "Adam learning rate of the log-radiance texels", "(0,1]")
    tv_weight: float = setting(1e-4, "weight of the smoothness term on neighbouring log-radiance texels")
    final_height: str = setting(
        "auto", "the learned envmap's last rung: auto stops at the rows the fitted roughness can resolve (read as "
                "the fit goes on), full at envmap.height", ("auto", "full"))


@dataclass
class LampConfig:
    """Point lamps fitted beside the envmap (a photograph's lamps at a finite distance)."""

    count: int = setting(0, "point lamps fitted beside the envmap (0: the envmap alone)", "[0,2]")
    frame: str = setting("world", "where the lamps stand: fixed in the world, or riding with each view's camera "
                                  "(a flash)", ("world", "camera"))
    distance: float = setting(2.0, "the lamps' starting distance from the object's centre, in object radii", ">1")
    lr: float = setting(0.02, "Adam learning rate of the lamps' positions (object radii) and log-intensities",
                        "(0,1]")


@dataclass
class LossConfig:
    """Loss weights of both branches (the paper's w1..w6)."""

    w_rec_c: float = setting(0.2, "w1: L2 reconstruction of the continuous branch")
    w_rec_d: float = setting(1.0, "w2: L2 reconstruction of the discrete branch")
    w_chr: float = setting(1.0, "w3: chromaticity of the discrete against the continuous basecolor")
    w_met: float = setting(1.0, "absolute difference of each hit's codeword metallic from the continuous one (0: off)")
    w_vq: float = setting(1.0, "w4: VQ (commitment) loss")
    w_lam: float = setting(1e-4, "w5: Lambertian prior (metallic towards 0, roughness towards 1)")
    lam_metallic: float = setting(2.0, "weight of the Lambertian prior's metallic term relative to its roughness term")
    lam_decay: float = setting(0.1, "w5 at the end of training relative to its start (1: constant)", "(0,1]")
    metallic_barrier_until: float = setting(0.3, "training share during which the metallic prior is -log(1 - metallic)",
                                                 "(0,1]")
    prior_evidence: str = setting(
        "auto", "auto weakens the Lambertian prior's metallic term where highlights keep the surface's colour, as "
                "a metal's do; off: the same weight everywhere", ("auto", "off"))
    w_sm: float = setting(0.0, "w6: colour-aware smoothness of neighbouring pixels (0: off)")
    sm_alpha: float = setting(60.0, "alpha of L_sm: how fast image differences switch the smoothness off")
    sm_beta: float = setting(0.1, "beta of L_sm: weight of metallic/roughness differences")
    gamma: float = setting(2.2, "reconstruction compares x^(1/gamma)", ">0")


@dataclass
class VQConfig:
    """The discrete branch: codebook, codeword dropout and the choice of the material count M."""

    enabled: bool = setting(True, "train the discrete branch and rank its codewords (false: continuous branch only)")
    num_codes: int = setting(8, "M0: codebook size", ">0")
    warmup_frac: float = setting(0.3, "share of training before the codebook starts (from k-means of the latents)",
                                      "[0,1]")
    decay: float = setting(0.99, "EMA decay of the codebook updates", "[0,1]")
    commitment: float = setting(0.1, "lambda of the VQ loss (Eq. 8)")
    dropout_max: float = setting(0.7, "codeword dropout rate of the last codeword (rates rise linearly to it)", "[0,1]")
    protected: int = setting(1, "first codewords that are never dropped")
    rank_eps: float = setting(0.002, "epsilon of the err_k rule that chooses M")
    rank_pixels: int = setting(4096, "training pixels on which err_k is measured", ">0")
    min_share: float = setting(0.005, "codewords chosen by fewer pixels than this share are not materials", "[0,1]")
    merge_tol: float = setting(
        0.1, "codewords decoding within this BRDF distance of a higher-ranked one are duplicates (0: off)")
    joint_scale: float = setting(0.05, "share of the discrete branch's gradient that reaches the shared encoder",
                                       "(0,1]")
    lam_decay: float = setting(0.1, "Lambertian prior decay on the discrete branch (1: constant)", "(0,1]")


@dataclass
class AblationConfig:
    """Switches of the paper's ablations; each preset ablation_* sets one."""

    no_ranking: bool = setting(False, "M = vq.num_codes, no dropout ranking")
    separate: bool = setting(False, "the discrete branch's gradients do not reach the encoder")
    single_branch: bool = setting(False, "after the warm-up, train the discrete branch alone")
    shared_light: bool = setting(False, "the discrete loss also trains the envmap and the bounce light")
    single_pass_ranking: bool = setting(False, "the paper's single ranking pass (no moving of redundant codewords)")


# The sizes that a 0 (auto) resolves to on a CPU; a GPU takes a multiple (`backend.sized`).
CPU_NEUS_BATCH, CPU_RENDER_CHUNK = 512, 65536


@dataclass
class TrainConfig:
    """The training loop."""

    iterations: int = setting(3000, "optimisation steps", ">0")
    batch_rays: int = setting(
        2048, "primary hits shaded per step: whole random foreground pixels from all training views", ">0")
    spp: int = setting(8, "emitter + BSDF sample pairs per pixel and step", ">0")
    lr: float = setting(2e-3, "Adam learning rate of the material networks", "(0,1]")
    lr_end_exponential: float = setting(
        0.1, "learning-rate factor reached at the last iteration (exponential in the steps done)", "(0,1]")
    seed: int = setting(0, "seed of the networks, batches and light samples")
    checkpoint_every: int = setting(500, "steps between checkpoints", ">0")
    log_every: int = setting(50, "steps between loss-curve entries", ">0")
    alpha_threshold: float = setting(0.99, "pixels with alpha below this are not fitted", "[0,1]")
    pixel_jitter: int = setting(4, "primary hits traced per pixel, stratified (0: the pixel centre)", "square")
    max_hits: int = setting(1 << 24, "most training hits kept (72 bytes each): fewer per pixel, then fewer pixels, "
                                     "above it (0: no limit)")
    bounces: int = setting(1, "interreflections simulated (0: direct light only)")
    bounce_after: int = setting(300, "steps of direct light only before the bounce is simulated")
    bounce: str = setting(
        "auto", "the bounce of train.bounces: auto turns it off where under 1 % of secondary rays from the training "
                "hits meet the object (decided at start-up)", ("auto", "on", "off"))
    trials: str = setting(
        "auto", "auto: under a learned light, a copy of the fit tries metals at the roughness floor as glossy and "
                "the held-aside pixels choose which goes on; off: no trial",
        ("auto", "off"))
    stop: str = setting(
        "iterations", "auto: the schedule speeds up as held-aside pixels stop improving and ends the fit (at most "
                      "train.iterations); iterations: train.iterations steps",
        ("auto", "iterations"))
    sampling: str = setting(
        "uniform", "which pixels a step draws: auto by their running error with a 30 % uniform share "
                "(importance-weighted), uniform all alike", ("auto", "uniform"))
    time_limit_s: float = setting(0.0, "stop after this many seconds (0: no limit)")
    snapshot_s: str = setting("", "comma-separated fit seconds at which a copy of the state is kept in snapshots/")


@dataclass
class ResidualConfig:
    """The view-dependent residual of novel views, fitted after the materials (VQ-NeRF, Sec. 4)."""

    iterations: int = setting(3000, "steps fitting the residual on the training pixels, materials and light frozen "
                                    "(0: no residual)")


@dataclass
class RenderConfig:
    """Rendering views of a fitted run."""

    spp: int = setting(256, "samples per pixel (primary rays x light samples)", ">0")
    aa: int = setting(16, "primary rays per pixel, stratified", "square>0")
    chunk: int = setting(0, "surface points shaded per Mitsuba call (0: auto, 65536 on a CPU, more on a GPU)", ">=0")


@dataclass
class NeuSConfig:
    """The geometry stage: NeuS on posed images (with masks or without), then mesh export."""

    seed: int = setting(0, "seed of the networks, ray batches and sample jitter")
    iterations: int = setting(0, "training steps (0: none, the time limit and the plateau end training; with no time "
                                 "limit 2 passes over the training rays within 4000-11000)", ">=0")
    time_limit_s: float = setting(480.0, "training seconds; the learning rate decays over them when neus.iterations is 0 "
                                         "(0: no limit)", ">=0")
    plateau_s: float = setting(60.0, "end training, after a short decay of the learning rate, once the held-aside "
                                     "rays gained under 0.05 dB over this many seconds (0: never)", ">=0")
    batch_rays: int = setting(0, "rays per step, drawn from all views (0: auto, 512 on a CPU, more on a GPU)", ">=0")
    n_samples: int = setting(24, "stratified samples per ray inside its occupied interval", ">0")
    lr: float = setting(1e-2, "Adam learning rate of the feature grids and the colour network", "(0,1]")
    lr_sdf_mlp: float = setting(1e-3, "Adam learning rate of the SDF MLP", "(0,1]")
    lr_variance: float = setting(2e-3, "Adam learning rate of the sharpness parameter", "(0,1]")
    lr_end_cosine: float = setting(
        0.1, "learning-rate factor reached at the last step (cosine in the steps done)", "(0,1]")
    warmup: int = setting(100, "steps of linear learning-rate warm-up")
    levels: int = setting(0, "resolution levels of the feature grid (0: auto, from the capture's resolution)", ">=0")
    base_res: int = setting(16, "coarsest grid resolution (points per axis)", ">0")
    max_res: int = setting(0, "finest grid resolution (0: auto, from the capture's resolution)", ">=0")
    features: int = setting(2, "features per grid level", ">0")
    hash_log2: int = setting(19, "a grid level with more points keeps 2^hash_log2 hashed entries (0: every level "
                                 "dense)", ">=0")
    hidden: int = setting(64, "width of the SDF and colour MLPs", ">0")
    sdf_layers: int = setting(0, "hidden layers of the SDF MLP (0: auto, 1 with the fine grid, else 2)", "[0,2]")
    geo_features: int = setting(15, "SDF-network features passed to the colour network")
    reflect: bool = setting(True, "the colour network sees the reflected view direction instead of the view direction")
    coarse_to_fine: float = setting(-1.0, "share of training over which finer grid levels fade in (-1: auto, 0 with the "
                                          "fine grid, else 0.3)", "-1|[0,1]")
    init: str = setting("hull", "SDF initialisation: hull (smoothed visual-hull distance) or sphere",
                                ("hull", "sphere"))
    init_radius: float = setting(0.0, "radius of the sphere initialisation (normalised box units; 0: 0.6 with "
                                      "masks, 0.3 of the bounding sphere without)", ">=0")
    init_variance: float = setting(0.5, "initial log-sharpness / 10 (s = exp(10 * variance))", "any")
    w_eikonal: float = setting(0.1, "eikonal loss weight")
    w_mask: float = setting(0.1, "mask loss weight (BCE on the accumulated opacity)")
    w_points: float = setting(0.5, "weight of the SDF-is-zero term at the capture's sparse points seen by 3 or more "
                                   "views, fading linearly to 0 over training (0: none)", ">=0")
    background: str = setting(
        "auto", "object or backdrop: masks (the capture's), model (a sphere framed from the cameras, a background "
                "model outside it) or auto (masks if any)", ("auto", "masks", "model"))
    hull_resolution: int = setting(128, "visual-hull / occupancy grid resolution", ">0")
    hull_threshold: float = setting(0.5, "alpha above which a pixel is foreground for carving", "[0,1]")
    hull_min_views: float = setting(0.3, "share of the views whose frusta must hold a voxel for it to be carved in",
                                          "[0,1]")
    occupancy_every: int = setting(500, "steps between occupancy-grid refreshes from the SDF")
    march_steps: int = setting(128, "coarse steps per ray that find its occupied interval", ">0")
    mesh_resolution: int = setting(256, "marching-cubes grid resolution", "[2,1024]")
    min_component: float = setting(0.05, "connected pieces smaller than this share of the largest are dropped", "[0,1]")
    keep_largest: bool = setting(False, "keep only the largest connected component")
    smooth_iterations: int = setting(0, "Taubin smoothing steps after marching cubes")
    normal_smoothing: int = setting(40, "vertex-normal averaging steps over edge neighbours (positions kept)")
    normal_smoothing_angle: float = setting(15.0, "neighbours whose normals differ by more (degrees) are not averaged")
    max_faces: int = setting(200000, "quadric decimation to this many faces (0: none)")
    checkpoint_every: int = setting(500, "steps between NeuS checkpoints")
    threads: int = setting(0, "torch CPU threads for NeuS (0: torch's count, every core or --threads)")


@dataclass
class CaptureConfig:
    """How a capture's images are read: their size, the mask, the views kept out of training."""

    downscale: int = setting(1, "divide the image width and height by this, averaging blocks of pixels", ">0")
    max_size: int = setting(0, "longest image side in pixels once read: each photo is area-averaged down to it "
                               "as it is read, after downscale (0: no limit)", ">=0")
    background_color: str = setting("", "R,G,B (sRGB, 0..1) of a plain backdrop, keyed out as the mask (\"\": none)")
    background_tolerance: float = setting(0.08, "sRGB distance from background_color still counted as backdrop",
                                                "[0,1]")
    holdout: int = setting(0, "keep every K-th view out of training, for `eval` to score (0: none)")


@dataclass
class PoseConfig:
    """Camera poses of photos or a video without them (structure from motion with COLMAP)."""

    matcher: str = setting("auto", "image pairs SfM matches: sequential (neighbours), exhaustive (all) or auto "
                                   "(sequential for a video or over 100 photos, else exhaustive)",
                           ("auto", "sequential", "exhaustive"))
    frames: int = setting(80, "frames kept from a video: the sharpest of each of this many equal time windows", ">0")
    min_registered: float = setting(0.5, "share of the images SfM must place (and at least 3), else it is refused",
                                    "[0,1]")


@dataclass
class Config:
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    envmap: EnvmapConfig = dataclasses.field(default_factory=EnvmapConfig)
    lamps: LampConfig = dataclasses.field(default_factory=LampConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    vq: VQConfig = dataclasses.field(default_factory=VQConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    residual: ResidualConfig = dataclasses.field(default_factory=ResidualConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    neus: NeuSConfig = dataclasses.field(default_factory=NeuSConfig)
    ablation: AblationConfig = dataclasses.field(default_factory=AblationConfig)
    capture: CaptureConfig = dataclasses.field(default_factory=CaptureConfig)
    pose: PoseConfig = dataclasses.field(default_factory=PoseConfig)


PRESETS_DIR = Path(str(resources.files("vq_mitsuba") / "presets"))  # package data, installed with the wheel


def presets() -> list[str]:
    """Names of the bundled presets (vq_mitsuba/presets/)."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def preset_path(name: str) -> Path:
    """vq_mitsuba/presets/NAME.yaml; an InputError listing the presets when there is none of that name
    (a name is one of `presets()`, never a path: '../presets/demo' is no preset)."""
    if name not in presets():
        raise InputError(None, f"unknown preset '{name}' (presets: {', '.join(presets())})")
    return PRESETS_DIR / f"{name}.yaml"


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def flat_keys(tree: dict, prefix: str = "") -> dict:
    """A nested config mapping (`to_dict`'s, or a YAML file's) as {"section.key": value}."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flat_keys(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _shown(value, limit: int = 60) -> str:
    """`value` as a message quotes it: its text, cut short past `limit` characters (a value of a
    hundred thousand aliased items is no message)."""
    text = str(value)
    return text if len(text) <= limit else text[:limit] + f"... ({len(text)} characters)"


# What YAML builds that no key takes, as a message names it (a key of text takes a date quoted: '2001-12-14').
_NOT_SCALARS = ((list, "a list"), (dict, "a mapping"), ((set, frozenset), "a set"), (bytes, "binary data"),
                ((datetime.date, datetime.datetime), "a date"))


def _coerce(value, typ, key: str, source):
    if typ is str and isinstance(value, bool):  # YAML reads on / off (and yes / no) as booleans
        return "on" if value else "off"
    what = next((w for kinds, w in _NOT_SCALARS if isinstance(value, kinds)), None)
    if what is not None:  # never the text of a list: "[30, 60]" would pass as a string
        expects = "text" if typ is str else typ.__name__
        raise InputError(source, f"'{key}' expects {expects}, got {what}: {_shown(value)}")
    if typ in (int, float) and isinstance(value, bool):  # YAML's true / false are not numbers
        raise InputError(source, f"'{key}' expects {typ.__name__}, got {str(value).lower()}")
    if typ is bool:
        if isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise InputError(source, f"'{key}' expects true/false, got '{_shown(value)}'")
        return bool(value)
    try:
        if typ is int and isinstance(value, float) and not value.is_integer():
            raise ValueError
        out = typ(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(source, f"'{key}' expects {typ.__name__}, got '{_shown(value)}'") from None
    if typ is float and not math.isfinite(out):
        raise InputError(source, f"'{key}' must be a finite number, got {_shown(value)}")
    if typ is int and abs(out) > MAX_INT:
        raise InputError(source, f"'{key}' must be a whole number within +-{MAX_INT}, got {_shown(value)}")
    return out


def _apply(cfg, data: dict, source, prefix: str = "") -> None:
    hints = typing.get_type_hints(type(cfg))
    for key, value in data.items():
        name = f"{prefix}{key}"
        if key not in hints:
            if name in _V1_RENAMED:
                raise InputError(source, f"'{name}' is now '{_V1_RENAMED[name]}'")
            known = ", ".join(hints)
            raise InputError(source, f"unknown config key '{name}' (known here: {known})")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError(source, f"'{name}' is a section; expected a mapping")
            _apply(current, value, source, name + ".")
        else:
            setattr(cfg, key, _coerce(value, hints[key], name, source))


# Bounds on every YAML file the tool reads (configs, presets, scenes, a run's config.yaml, --set
# values): each of these is a few KB, and aliases let a 1 KB file stand for billions of values.
MAX_YAML_BYTES = 1 << 20
MAX_YAML_NODES = 100_000  # values once every alias is expanded


class _YAMLRefused(Exception):
    """A YAML document refused by _BoundedLoader: the message says why, in words."""


class _BoundedLoader(yaml.SafeLoader):
    """YAML's safe loader with bounds: a document whose aliases expand past MAX_YAML_NODES values or
    refer to themselves is refused before it is built, so is a key given twice in one mapping (YAML
    would keep the last) and a merge key (`<<`)."""

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None:
            _check_expanded_size(node)
        return node

    def construct_object(self, node, deep=False):
        try:
            return super().construct_object(node, deep=deep)
        except (ValueError, TypeError, KeyError, AttributeError, IndexError) as exc:  # PyYAML's constructors
            raise _YAMLRefused(_unreadable(node, exc)) from None

    def construct_mapping(self, node, deep=False):
        if not isinstance(node, yaml.MappingNode):  # "!!set [1]": PyYAML says what it expected
            return super().construct_mapping(node, deep=deep)
        seen = {}
        for key_node, _ in node.value:
            line = key_node.start_mark.line + 1
            if key_node.tag == "tag:yaml.org,2002:merge":
                raise _YAMLRefused(f"line {line}: a YAML merge key ('<<') is not supported; write the keys out in full")
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, typing.Hashable):
                raise _YAMLRefused(f"line {line}: a key is a list or a mapping; keys are plain values")
            if key in seen:
                raise _YAMLRefused(f"'{key}' is given twice (lines {seen[key]} and {line})")
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


# What a value of each YAML tag must be, as a message says it.
_TAG_WORDS = {"int": "a whole number", "float": "a number", "bool": "true or false", "timestamp": "a date",
              "null": "empty", "binary": "base64 data"}


def _unreadable(node, exc: Exception) -> str:
    """Why a value (a node whose constructor failed: "!!bool x", "!!float x", a date of month 13, a
    whole number of more than 4300 digits) cannot be read, in words, with its line."""
    kind = node.tag.rsplit(":", 1)[-1]
    what = _TAG_WORDS.get(kind, f"a !!{kind}")
    shown = repr(_shown(node.value)) if isinstance(node.value, str) else "this value"
    why = ("more than 4300 digits" if "integer string conversion" in str(exc)
           else str(exc) if kind == "timestamp" and isinstance(exc, ValueError) else "")
    return f"line {node.start_mark.line + 1}: {shown} cannot be read as {what}" + (f" ({why})" if why else "")


def _children(node) -> list:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return list(node.value) if isinstance(node, yaml.SequenceNode) else []


def _check_expanded_size(root) -> None:
    """Refuse a node graph whose tree, every alias expanded, has more than MAX_YAML_NODES nodes or
    no end (an alias inside the node it names). Each shared node is counted once per use, in time
    linear in the distinct nodes."""
    sizes: dict[int, int] = {}
    open_: set[int] = set()
    stack = [(root, False)]
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            open_.discard(key)
            sizes[key] = 1 + sum(sizes[id(c)] for c in _children(node))
            if sizes[key] > MAX_YAML_NODES:
                raise _YAMLRefused(f"holds more than {MAX_YAML_NODES} values once its aliases are expanded "
                                   f"(line {node.start_mark.line + 1})")
        elif key not in sizes:
            if key in open_:
                raise _YAMLRefused(f"line {node.start_mark.line + 1}: an alias refers to the value that holds it")
            open_.add(key)
            stack.append((node, True))
            stack.extend((c, False) for c in _children(node) if id(c) not in sizes)


def _yaml_error_text(exc: yaml.YAMLError) -> str:
    """A parser's error as one sentence with its line, without PyYAML's stream name."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    context, context_mark = getattr(exc, "context", None), getattr(exc, "context_mark", None)
    if context and context_mark is not None:
        context += f" from line {context_mark.line + 1}"
    return f"invalid YAML: {where}{problem}" + (f" ({context})" if context else "")


def parse_yaml(text: str, source) -> object:
    """`text` as YAML through the bounded loader; InputError naming `source` (a file or an option)
    when it is not YAML or exceeds a bound."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)
    except _YAMLRefused as exc:
        raise InputError(source, str(exc)) from None
    except yaml.YAMLError as exc:
        raise InputError(source, _yaml_error_text(exc)) from None
    except RecursionError:
        raise InputError(source, "invalid YAML: nested too deep") from None


def read_yaml(path: str | Path, what: str = "a YAML file") -> object:
    """A YAML file through the bounded loader (at most MAX_YAML_BYTES); InputError naming the file
    when it is missing, too large, not UTF-8 or not YAML. `what` says what the file should be."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, f"is a folder: expected {what}")
    if not path.is_file():
        raise InputError(path, "not found")
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise InputError(path, f"cannot be read: {exc.strerror}") from None
    if len(raw) > MAX_YAML_BYTES:
        raise InputError(path, f"is larger than {MAX_YAML_BYTES // 1024} KB: {what} is a few KB of YAML text")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(path, f"is not UTF-8 text (byte {exc.start}): {what} is YAML text") from None
    return parse_yaml(text, path)


def read_config_file(path: str | Path) -> dict:
    """A YAML config file as a mapping of sections; InputError naming the file otherwise."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, "is a folder: --config takes a YAML file")
    if not path.is_file():
        raise InputError(path, "config file not found")
    data = read_yaml(path, "a config file") or {}
    if not isinstance(data, dict):
        raise InputError(path, "expected a mapping of sections")
    return data


def _section_name(cls) -> str:
    """`neus` for NeuSConfig: the name under which Config holds a section ("" for Config itself)."""
    for f in dataclasses.fields(Config):
        if f.default_factory is cls:
            return f.name
    return ""


def _value_error(key: str, value, range_) -> str | None:
    """The message for a value outside its key's range (None when it is inside)."""
    if isinstance(value, bool) or range_ is None:
        return None
    if isinstance(range_, tuple):
        if value in range_:
            return None
        return f"{key} must be one of {', '.join(repr(c) for c in range_)}, got {_shown(repr(value))}"
    if isinstance(value, str):
        return None  # free text, parsed where it is used
    test, phrase = RANGES[range_]
    return None if test(value) else f"{key} must be {phrase}, got {value}"


def check(cfg, source=None, prefix: str | None = None) -> None:
    """The one validator: every key of `cfg` (a Config or one section) inside the range its
    metadata gives, then the checks that span keys. `source` is the layer that set the values (a
    file or --set): the InputError names it."""
    if prefix is None:
        name = _section_name(type(cfg))
        prefix = f"{name}." if name else ""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            check(value, source, f"{prefix}{f.name}.")
            continue
        message = _value_error(prefix + f.name, value, f.metadata.get("range"))
        if message:
            raise InputError(source, message)
    if isinstance(cfg, NeuSConfig) and (cfg.base_res < 2 or 0 < cfg.max_res < cfg.base_res):
        raise InputError(source, f"{prefix}base_res must be >= 2 and {prefix}max_res 0 or >= {prefix}base_res, got "
                                 f"{prefix}base_res={cfg.base_res}, {prefix}max_res={cfg.max_res}")
    if isinstance(cfg, CaptureConfig) and cfg.background_color:
        background_rgb(cfg, source)


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


def parse_overrides(overrides: list[str] | None) -> dict:
    """`section.key=value` items (values parsed as YAML) as a nested mapping."""
    nested: dict = {}
    for item in overrides or []:
        if "=" not in item:
            raise InputError(None, f"--set expects key=value, got '{_shown(item)}'")
        key, value = item.split("=", 1)
        if not value.strip():
            raise InputError(None, f"--set {_shown(item)}: the value is empty (give one after '=')")
        parts = key.strip().split(".")
        cur = nested
        for part in parts[:-1]:
            cur = cur.setdefault(part, {})
            if not isinstance(cur, dict):
                raise InputError(None, f"--set {key}: '{part}' is a key, not a section")
        cur[parts[-1]] = parse_yaml(value, f"--set {key.strip()}")
    return nested


# config.yaml's format. 2: train.lr_decay and neus.lr_decay became train.lr_end_exponential and
# neus.lr_end_cosine, and the `texel` section left Config (it is vq_mitsuba.eval.texel.TexelConfig).
CONFIG_VERSION = 2
_V1_RENAMED = {"train.lr_decay": "train.lr_end_exponential", "neus.lr_decay": "neus.lr_end_cosine"}
_V1_DROPPED = ("texel",)


def _v1_to_v2(data: dict) -> dict:
    out = {}
    for name, section in data.items():
        if name in _V1_DROPPED:
            continue
        if isinstance(section, dict):
            section = {_V1_RENAMED.get(f"{name}.{key}", f"{name}.{key}").split(".", 1)[1]: value
                       for key, value in section.items()}
        out[name] = section
    return out


_UPGRADES = {1: _v1_to_v2}


def upgrade(data: dict, source=None, default_version: int = 1) -> dict:
    """A saved config mapping in the current format: its `version` (absent: `default_version`) is
    removed and each step from there to CONFIG_VERSION applied."""
    data = dict(data)
    version = data.pop("version", default_version)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise InputError(source, f"config version must be a whole number from 1 to {CONFIG_VERSION}, got {version!r}")
    if version > CONFIG_VERSION:
        raise InputError(source, f"config version {version} is newer than this vq-mitsuba reads "
                                 f"({CONFIG_VERSION}); update vq-mitsuba")
    while version < CONFIG_VERSION:
        data = _UPGRADES[version](data)
        version += 1
    return data


def load_config(path: str | Path | None = None, overrides: list[str] | None = None, base: dict | None = None,
                preset: str | None = None) -> Config:
    """Defaults <- `base` (a run's saved config) <- preset PRESET <- YAML file <- `key=value`
    overrides; each layer is checked as it is applied, and an error names the layer.

    `base` without a `version` is a version 1 config.yaml and is upgraded; a file with a `version`
    (a copied config.yaml) is upgraded from it, one without is in the current format."""
    cfg = Config()
    layers: list[tuple[object, dict]] = []
    if base:
        layers.append(("config.yaml", upgrade(base, "config.yaml")))
    if preset is not None:
        path_p = preset_path(preset)
        layers.append((path_p, read_config_file(path_p)))
    if path is not None:
        layers.append((path, read_config_file(path)))
    if overrides:
        layers.append(("--set", parse_overrides(overrides)))
    for source, data in layers:
        if source != "config.yaml" and "version" in data:
            data = upgrade(data, source, CONFIG_VERSION)
        _apply(cfg, data, source)
        check(cfg, source)
    return cfg


def save_config(cfg: Config, path: str | Path) -> None:
    """config.yaml: `version: CONFIG_VERSION`, then every section."""
    Path(path).write_text(yaml.safe_dump({"version": CONFIG_VERSION, **to_dict(cfg)}, sort_keys=False))


def range_text(default, range_) -> str:
    """A key's range as --help-config and docs/configuration.md show it."""
    if range_ is None:
        return "true/false"
    if isinstance(range_, tuple):
        return " or ".join(range_)
    if isinstance(default, str):
        return "text"
    return {"any": "any", "square": "square number or 0", "square>0": "square number > 0"}.get(
        range_, RANGES[range_][1].removeprefix("in "))


def _default(f: dataclasses.Field):
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def _doc(f: dataclasses.Field) -> tuple[str, str]:
    """A key's (help, range text), from its metadata."""
    return f.metadata.get("help", ""), range_text(_default(f), f.metadata.get("range"))


def describe(cfg_cls=Config, prefix: str = "") -> list[str]:
    """One line per key, `  section.key = default (range): meaning`, under a line per section, for --help-config."""
    lines = []
    for f in dataclasses.fields(cfg_cls):
        default = _default(f)
        if dataclasses.is_dataclass(default):
            doc = (type(default).__doc__ or "").strip().splitlines()[0]
            lines.append(f"{prefix}{f.name}: {doc}")
            lines += describe(type(default), prefix + f.name + ".")
        else:
            help_, shown = _doc(f)
            lines.append(f"  {prefix}{f.name} = {default!r} ({shown}): {help_}")
    return lines


def markdown() -> str:
    """docs/configuration.md: every key, generated from this module (`python -m vq_mitsuba.config`)."""
    lines = ["# Configuration", "",
             "Generated by `python -m vq_mitsuba.config > docs/configuration.md` from `vq_mitsuba/config.py`; "
             "`vq-mitsuba fit --help-config` prints the same. A run's config is the defaults, then "
             "`--preset NAME` (a bundled preset, `fit --help-config` lists them), then `--config FILE`, then "
             "each `--set section.key=value`. "
             "Every value is checked against its range as its layer is applied; an error names the layer. "
             f"A config file is YAML text of at most {MAX_YAML_BYTES // 1024} KB; a key given twice, a merge key "
             f"(`<<`) and aliases that expand to more than {MAX_YAML_NODES} values are refused.",
             "",
             f"A run's `config.yaml` starts with `version: {CONFIG_VERSION}`; one without a version (version 1) "
             "is read with its old names: `" + "`, `".join(f"{old}` as `{new}" for old, new in _V1_RENAMED.items())
             + "`, and its `texel` section ignored (the per-texel baseline's settings are `TexelConfig` in "
             "`vq_mitsuba/eval/texel.py`).",
             ""]
    for f in dataclasses.fields(Config):
        section = _default(f)
        lines += [f"## `{f.name}`: {(type(section).__doc__ or '').strip()}", "",
                  "| key | default | range | meaning |", "|---|---|---|---|"]
        for g in dataclasses.fields(section):
            help_, shown = _doc(g)
            lines.append(f"| `{f.name}.{g.name}` | `{getattr(section, g.name)!r}` | {shown} | {help_} |")
        lines.append("")
    lines += ["## Presets", ""] + [f"- `{name}`: " + (preset_path(name).read_text().splitlines()[0].lstrip("# ")
                                                       if preset_path(name).read_text().startswith("#") else "")
                                   for name in presets()]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
