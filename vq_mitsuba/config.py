"""Typed configuration: one dataclass per component; YAML presets and `--set key=value` overrides.

Every field's comment is its documentation (`vq-mitsuba fit --help-config` prints them).
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from pathlib import Path

import yaml

from .errors import InputError


@dataclass
class FieldConfig:
    pe_freqs: int = 8  # positional-encoding frequencies of the surface point
    hidden: int = 128  # width of the encoder's 7 FC layers (paper: 256)
    latent: int = 16  # dimension of the latent z
    decoder_hidden: int = 64  # width of each decoder MLP (3 FC layers with a skip)
    roughness_min: float = 0.02  # roughness output range is [roughness_min, 1]
    pe_anneal: float = 0.5  # fraction of training over which encoding frequencies open (0: all at once)
    pe_anneal_iterations: bool = False  # open the frequencies with the share of train.iterations done, also under a time limit (off: with the training progress, which under train.time_limit_s follows the clock, so a short budget opens them all)
    metallic_delay: float = 0.0  # fraction of training with metallic held at 0 (dielectric first); it then fades in over as long again (0: no delay)
    metallic_init: float = 0.02  # metallic output at initialisation, through the last layer's bias (0: PyTorch's default initialisation, about 0.5)


@dataclass
class EnvmapConfig:
    height: int = 32  # rows of the learned lat-long envmap (width is twice this)
    init_scale: float = 2.0  # initial radiance = init_scale x mean foreground pixel value
    lr: float = 0.02  # Adam learning rate of the log-radiance texels
    tv_weight: float = 1e-4  # smoothness of the log radiance (neighbouring texels)


@dataclass
class LossConfig:
    w_rec_c: float = 0.2  # w1: L2 reconstruction of the continuous branch
    w_lam: float = 1e-4  # w5: Lambertian prior (metallic -> 0, roughness -> 1); the paper's 0.001 is for its loss scale and saturates roughness at 1 with ours
    lam_metallic: float = 2.0  # weight of L_lam's metallic term relative to its roughness term (the paper: 1; 2 keeps balls' glossy plastic dielectric, 3 lowers demo's partly metallic torus)
    lam_decay: float = 0.1  # w5 at the end of training relative to its start, decayed like the learning rate (1: constant): the prior settles ambiguities early, then biases converged materials less towards rough
    metallic_barrier: bool = True  # L_lam's metallic term as -log(1 - metallic) (false: metallic, the paper's): its pull on the metallic logit does not vanish where metallic saturates at 1, so a glossy dielectric does not saturate as a rough metal while the encoding is still coarse (balls' green plastic)
    metallic_barrier_until: float = 0.3  # training progress in (0, 1] up to which loss.metallic_barrier applies, after it the paper's linear term: the barrier holds while the encoding is coarse (where balls' green plastic saturated as a metal) and then stops pulling true metals down (balls: metals 0.94-0.98 instead of 0.90-0.93); 1: the whole fit
    decorrelated: bool = True  # L_rec from two independent half-estimates (no bias towards low-variance materials)
    w_rec_d: float = 1.0  # w2: L2 reconstruction of the discrete branch
    w_chr: float = 1.0  # w3: chromaticity of discrete vs continuous basecolor
    w_vq: float = 1.0  # w4: VQ (commitment) loss
    w_sm: float = 0.0  # w6: colour-aware smoothness on neighbouring pixels (paper: 0.05; at our loss scale it over-smooths, see README)
    sm_alpha: float = 60.0  # alpha: how fast image differences switch the smoothness off
    sm_beta: float = 0.1  # beta: weight of metallic/roughness differences in L_sm
    gamma: float = 2.2  # reconstruction is compared on x^(1/gamma): HDR highlights do not dominate


@dataclass
class VQConfig:
    enabled: bool = False  # train the discrete branch (experimental; off: continuous branch only, the "single branch" ablation)
    num_codes: int = 8  # M0: codebook size (15 for complex scenes)
    warmup_frac: float = 0.3  # continuous-only warm-up, then the codebook starts from k-means of the latents
    decay: float = 0.99  # EMA decay of the codebook updates
    commitment: float = 0.1  # lambda of the VQ loss (Eq. 8)
    dropout_max: float = 0.7  # codeword dropout rates rise linearly from 0 to this over the codebook
    protected: int = 1  # first codewords that are never dropped
    ranking: bool = True  # choose M with the err_k rule (off: M = num_codes, the "no ranking" ablation)
    rank_eps: float = 0.002  # epsilon of the err_k flattening rule
    rank_pixels: int = 4096  # training pixels used to measure err_k
    min_share: float = 0.005  # codewords picked by fewer pixels than this share are not ranked as materials
    merge_tol: float = 0.1  # a codeword decoding to within this of a higher-ranked one's BRDF (gamma basecolor, metallic, roughness; max abs difference) is a duplicate, ranked behind the distinct ones (0: off)
    redundant_last: bool = True  # a codeword inside the chosen prefix that lowers err_k by less than rank_eps moves to the end and err_k is measured again (off: the paper's single pass)
    joint: bool = True  # discrete gradients also train the encoder (off: "separate" training)
    joint_scale: float = 0.05  # with vq.joint, the share in (0, 1] of the discrete branch's gradients (straight-through and commitment) that reaches the shared encoder; 1: the paper's joint training, under which the discrete loss (w2 = 5 w1) dominates the encoder and costs the continuous basecolor (texture at 128 px, 300 s: 25.7 against 30.7 dB alone; 0.2 still cost it 3.8 dB with seed 0)
    lam_decay: float = 0.1  # the Lambertian prior's decay on the discrete branch, like loss.lam_decay on the continuous one (1: constant)
    light_from_continuous: bool = True  # the discrete branch is rendered under the environment map and indirect bounce that the continuous branch fits, without training them (off: its loss trains them too, the paper's shared light)
    warm_start_decoder: bool = True  # the discrete decoder starts as a copy of the continuous one (off: random)
    forced_gradient: bool = False  # straight-through gradient also for latents that dropout forced onto another codeword (on: their discrete loss moves the encoder towards a material that is not theirs)
    single_branch: bool = False  # after warm-up, train the discrete branch alone (no L_rec,c, no L_chr): an ablation


@dataclass
class TrainConfig:
    iterations: int = 3000  # optimisation steps
    batch_rays: int = 2048  # random foreground pixels per step, drawn across all training views
    spp: int = 8  # emitter + BSDF sample pairs per pixel and step
    lr: float = 2e-3  # Adam learning rate of the material fields
    lr_decay: float = 0.1  # learning rates decay exponentially to this fraction at the end
    lr_decay_iterations: bool = True  # the learning rates decay with the share of train.iterations done, also under a time limit, so a fit the clock stops early ends at a higher rate (off: with the training progress, which under train.time_limit_s follows the clock: a 30 s fit then spends most of its few steps at a small rate, and lost 5.5 to 7.6 dB of basecolor against a constant rate on balls and texture at 128 px)
    seed: int = 0  # seeds torch (networks, batches, light samples)
    checkpoint_every: int = 500  # steps between checkpoints (a run resumes from the last one)
    log_every: int = 50  # steps between loss-curve entries
    alpha_threshold: float = 0.99  # pixels with alpha below this are not used for the loss
    pixel_jitter: int = 4  # primary hits traced per pixel, stratified (a square number; 0: pixel centre only)
    footprint: bool = False  # a pixel's spp samples are spread over its jittered hits (materials: train.footprint_per_hit): the loss compares pixel averages, so sharp reflections are not fitted rougher to cut the variance across the pixel
    footprint_per_hit: bool = True  # with train.footprint, the material field is evaluated at every jittered hit of the pixel (false: the first hit's material for all of them, as before); a texture edge inside a pixel is then fitted as such
    bounces: int = 1  # interreflections simulated (0: direct light only, 1: one bounce off the object)
    bounce_after: int = 300  # training steps before train.bounces are simulated: the first ones shade direct light only, each about 1.3x faster (0: the bounce from the first step); a short train.time_limit_s gets more steps, and the early materials are far from needing the bounce
    time_limit_s: float = 0.0  # stop after this many seconds (0: no limit); the other schedules then follow the clock when it runs ahead of the iterations
    snapshot_s: str = ""  # comma-separated fit seconds at which to keep a copy of the state in snapshots/ (time-vs-error curves)


@dataclass
class RenderConfig:
    spp: int = 256  # samples per pixel when rendering views (primary rays x light samples)
    aa: int = 16  # primary rays per pixel, stratified over the pixel (a square number)
    chunk: int = 65536  # surface points shaded per Mitsuba call (more: fewer calls, more memory)


@dataclass
class Config:
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    envmap: EnvmapConfig = dataclasses.field(default_factory=EnvmapConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    vq: VQConfig = dataclasses.field(default_factory=VQConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)


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
        return typ(value)
    except (TypeError, ValueError):
        raise InputError(source, f"'{key}' expects {typ.__name__}, got '{value}'") from None


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


def _check_ranges(cfg: Config, source) -> None:
    """Values that parse but make no sense; `source` is the layer that set them (file or --set)."""
    if not 0.0 <= cfg.field.metallic_init < 1.0:
        raise InputError(source, f"field.metallic_init must be in [0, 1) (0: default initialisation), got {cfg.field.metallic_init}")
    per_set = cfg.train.spp // (2 if cfg.loss.decorrelated else 1)
    if cfg.train.footprint and cfg.train.pixel_jitter > 1 and per_set % cfg.train.pixel_jitter != 0:
        raise InputError(source, f"train.footprint spreads each sample set ({per_set} samples: train.spp"
                         f"{' / 2, loss.decorrelated' if cfg.loss.decorrelated else ''}) over train.pixel_jitter = "
                         f"{cfg.train.pixel_jitter} hits: make it a multiple of pixel_jitter")
    for key, value, one in (("loss.lam_decay", cfg.loss.lam_decay, "a constant Lambertian prior"),
                            ("vq.lam_decay", cfg.vq.lam_decay, "a constant Lambertian prior"),
                            ("vq.joint_scale", cfg.vq.joint_scale, "the full joint gradient"),
                            ("loss.metallic_barrier_until", cfg.loss.metallic_barrier_until, "the whole fit")):
        if not 0.0 < value <= 1.0:
            raise InputError(source, f"{key} must be in (0, 1] (1: {one}), got {value}")
    if cfg.train.bounce_after < 0:
        raise InputError(source, f"train.bounce_after must be >= 0 steps (0: bounces from the first step), "
                         f"got {cfg.train.bounce_after}")


def load_config(path: str | Path | None = None, overrides: list[str] | None = None, base: dict | None = None) -> Config:
    """Defaults <- `base` (e.g. a run's saved config) <- YAML file <- `key=value` overrides."""
    cfg = Config()
    if base:
        _apply(cfg, base, "config.yaml")
        _check_ranges(cfg, "config.yaml")
    if path is not None:
        data = read_config_file(path)
        data.pop("neus", None)  # the geometry stage's section (vq_mitsuba.geometry.config)
        _apply(cfg, data, path)
        _check_ranges(cfg, path)
    for item in overrides or []:
        if "=" not in item:
            raise InputError(None, f"--set expects key=value, got '{item}'")
        key, value = item.split("=", 1)
        parts = key.strip().split(".")
        nested: dict = {}
        cur = nested
        for p in parts[:-1]:
            cur = cur.setdefault(p, {})
        cur[parts[-1]] = yaml.safe_load(value)
        _apply(cfg, nested, "--set")
        _check_ranges(cfg, "--set")
    return cfg


def save_config(cfg: Config, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(to_dict(cfg), sort_keys=False))


def describe(cfg_cls=Config, prefix: str = "") -> list[str]:
    """Lines `section.key (default): comment` for --help, read from the field comments."""
    import inspect

    lines = []
    src = inspect.getsource(cfg_cls)
    comments = {}
    for line in src.splitlines():
        if ":" in line and "#" in line and "=" in line:
            name = line.split(":")[0].strip()
            comments[name] = line.split("#", 1)[1].strip()
    for f in dataclasses.fields(cfg_cls):
        default = f.default_factory() if f.default is dataclasses.MISSING else f.default
        if dataclasses.is_dataclass(default):
            lines += describe(type(default), prefix + f.name + ".")
        else:
            lines.append(f"  {prefix}{f.name} = {default!r}: {comments.get(f.name, '')}")
    return lines
