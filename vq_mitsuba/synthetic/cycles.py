"""Bundled synthetic scenes rendered with Blender Cycles instead of Mitsuba (`make-scene --renderer cycles`).

Blender-as-a-module (`bpy`) needs numpy < 2, which the project's environment does not have, so it
lives in its own environment `.venv-cycles` (`make cycles`) and renders in a subprocess running
`vq_mitsuba/synthetic/cycles_worker.py`. This module does everything else with the same building blocks as
`vq_mitsuba.synthetic.mitsuba_scenes`: scene spec, geometry, cameras, envmaps, transforms json, scene.xml. It
writes a job file (`_cycles/job.json`), runs the worker, and turns the worker's multilayer EXRs
into the layout `synthetic.make_scene` writes (`vq_mitsuba.data.dataset_dir.DatasetDir`), so `fit`,
`render` and `eval` read a Cycles dataset exactly like a Mitsuba one:

    images/<id>.exr, .png        Combined pass (linear premultiplied RGBA / sRGB straight alpha)
    gt/<id>_basecolor.exr ...    shader AOVs basecolor, metallic, roughness divided by coverage
    gt/<id>_normal.exr           Normal pass (Blender world), renormalised
    gt/<id>_material.png         material index pass (material k of the spec = k + 1, 0 = background),
                                 0 where the coverage is below one half
    gt/<id>_alpha.png            coverage (the Combined alpha of the transparent film)
    relit/<env>/<id>.exr, .png   test views under each held-aside envmap and Blender's eight
                                 studio-light probes (copied to envmaps/blender_<probe>.exr)

Cycles settings: CPU, Principled BSDF with single-scatter GGX, IOR 1.5, Specular IOR Level 0.5,
max_bounces MAX_BOUNCES (Mitsuba's max_depth 4 counts the camera segment and the emitter hit:
the same paths), no clamping, no glossy blur, no adaptive sampling, denoiser off, 1-pixel box
pixel filter, transparent film, view transform Standard. The envmap lights the Blender-world
scene through an Environment Texture node with no mapping: Cycles' equirectangular lookup is the
convention of `vq_mitsuba.data.envmaps` (centre = +X, u = 0.25 = +Y, top = +Z).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np

from vq_mitsuba import brdf
from vq_mitsuba.backend import init_mitsuba
from vq_mitsuba.data import envmaps
from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.errors import InputError
from vq_mitsuba.synthetic import mitsuba_scenes as synthetic

_ROOT = Path(__file__).resolve().parents[2]
CHECKOUT = _ROOT if (_ROOT / "pyproject.toml").is_file() else None  # None when installed from the wheel
WORKER = Path(__file__).resolve().parent / "cycles_worker.py"
ENV_VAR = "VQ_CYCLES_PYTHON"  # overrides the interpreter that has bpy
MAX_BOUNCES = synthetic.MAX_DEPTH - 2
DEFAULT_SPP = 128
INDEX_PASS = "Material Index"  # Cycles' material index pass (IndexMA) in a Blender 5 EXR
WORK_DIR = DatasetDir.CYCLES_WORK  # job file and raw multilayer EXRs inside the dataset (removed unless keep_raw)


# --------------------------------------------------------------------------------------------
# The Blender environment
# --------------------------------------------------------------------------------------------
def cycles_python() -> Path:
    """The interpreter of the environment with bpy: $VQ_CYCLES_PYTHON, else .venv-cycles/bin/python of
    the checkout (of the working folder when installed from the wheel)."""
    env = os.environ.get(ENV_VAR)
    return Path(env) if env else (CHECKOUT or Path.cwd()) / ".venv-cycles" / "bin" / "python"


def _site_packages(python: Path) -> list[Path]:
    prefix = python.parent.parent
    return sorted(prefix.glob("lib/python3*/site-packages")) + sorted(prefix.glob("Lib/site-packages"))


def bpy_dir(python: Path | None = None) -> Path | None:
    """The `bpy` package folder of the Cycles environment, or None."""
    python = python or cycles_python()
    for sp in _site_packages(python):
        if any((sp / "bpy").glob("__init__.*")):
            return sp / "bpy"
    return None


def check_environment() -> Path:
    """The Cycles interpreter; InputError with the fix when it or its bpy is missing."""
    python = cycles_python()
    hint = "run `make cycles` to create .venv-cycles with Blender's bpy module"
    if os.environ.get(ENV_VAR):
        hint = f"{ENV_VAR} points to it; unset it to use .venv-cycles, or {hint}"
    if not python.is_file():
        raise InputError(python, f"no Python with bpy for --renderer cycles ({hint})")
    if bpy_dir(python) is None:
        raise InputError(python, f"this environment has no bpy module ({hint})")
    return python


def blender_probes(python: Path | None = None) -> dict[str, Path]:
    """Blender's eight CC0 studio-light HDRs (name -> path) shipped with bpy in the Cycles environment."""
    root = bpy_dir(python)
    if root is None:
        return {}
    return {p.stem: p for p in sorted(root.glob("*/datafiles/studiolights/world/*.exr"))}


def load_probe(path: str | Path) -> np.ndarray:
    """A Blender studio-light probe as float32 (H, W, 3) (envmaps.load_envmap: the probes' few
    tiny negative texels, down to about -0.002, are clamped to 0)."""
    return envmaps.load_envmap(path)


# --------------------------------------------------------------------------------------------
# The job file
# --------------------------------------------------------------------------------------------
def _round(a: np.ndarray, digits: int = 7) -> list:
    return np.round(np.asarray(a, dtype=np.float64), digits).tolist()


def build_job(spec: dict, shapes: list[dict], cameras: list, renders: list[dict], spp: int, seed: int = 0,
              denoise: bool = False, threads: int = 0) -> dict:
    """The worker's job (JSON-serialisable), everything in Blender world.

    shapes: [{name, material, vertices (V,3), faces (F,3), normals (V,3)}] from synthetic.build_shape;
    cameras: synthetic Camera objects (Mitsuba camera axes, Blender world); renders: [{camera,
    envmap, output}]. Material k of the spec gets id k + 1 (the material index pass), as the
    Mitsuba generator numbers gt/<id>_material.png. A patterned base_color is baked into
    per-vertex colours with synthetic.eval_base_color, as the Mitsuba generator does.
    """
    from vq_mitsuba.data.cameras import camera_to_nerf

    mats = {m["name"]: m for m in spec["materials"]}
    job_mats = []
    for k, m in enumerate(spec["materials"]):
        tex = synthetic.is_textured(m)
        values = {i.principled: None if tex and i.principled == synthetic.BASE_COLOR  # baked per vertex
                  else [float(c) for c in m[i.principled]] if i.colour else float(m[i.principled])
                  for i in brdf.INPUTS}
        job_mats.append({"name": m["name"], "id": k + 1, **values, "vertex_colors": tex})
    job_shapes = []
    for s in shapes:
        mat = mats.get(s["material"])
        if mat is None:
            raise InputError(None, f"shape {s['name']} uses unknown material {s['material']!r}")
        v = np.asarray(s["vertices"], dtype=np.float64)
        f = np.asarray(s["faces"], dtype=np.int64)
        n = np.asarray(s["normals"], dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or n.shape != v.shape or f.ndim != 2 or f.shape[1] != 3:
            raise InputError(None, f"shape {s['name']}: vertices/normals must be (V, 3) and faces (F, 3)")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise InputError(None, f"shape {s['name']}: face index out of range")
        colors = synthetic.eval_base_color(mat[synthetic.BASE_COLOR], v) if synthetic.is_textured(mat) else None
        job_shapes.append({"name": s["name"], "material": s["material"], "vertices": _round(v),
                           "faces": f.tolist(), "normals": _round(n),
                           "colors": None if colors is None else _round(colors, 6)})
    job_cams = []
    for cam in cameras:
        m, angle = camera_to_nerf(cam)
        job_cams.append({"name": cam.name, "transform_matrix": m.tolist(), "camera_angle_x": angle,
                         "width": int(cam.width), "height": int(cam.height)})
    names = {c["name"] for c in job_cams}
    for r in renders:
        if r["camera"] not in names:
            raise InputError(None, f"render of unknown camera {r['camera']!r}")
    return {"version": 1,
            "render": {"samples": int(spp), "seed": int(seed), "max_bounces": MAX_BOUNCES, "denoise": bool(denoise),
                       "filter_width": 1.0, "threads": int(threads)},
            "inputs": [{"name": i.name, "channels": i.channels, "principled": i.principled, "blender": i.blender,
                        "patterned": i.principled == synthetic.BASE_COLOR} for i in brdf.INPUTS],
            "materials": job_mats, "shapes": job_shapes, "cameras": job_cams,
            "renders": [{"camera": r["camera"], "envmap": str(r["envmap"]), "output": str(r["output"])}
                        for r in renders]}


def run_worker(job: dict, job_path: Path, on_view=None, python: Path | None = None) -> None:
    """Write the job and render it in the Cycles environment; `on_view(1)` after each render."""
    python = python or check_environment()
    job_path = Path(job_path)
    job_path.parent.mkdir(parents=True, exist_ok=True)
    job_path.write_text(json.dumps(job))
    log_path = job_path.with_suffix(".log")
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)  # the worker must not see the main environment's packages
    # -I: isolated mode, so the script's folder (vq_mitsuba/, whose cycles.py would shadow Blender's
    # `cycles` add-on) is not put on sys.path.
    with open(log_path, "w") as log:
        proc = subprocess.Popen([str(python), "-I", str(WORKER), str(job_path)], stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env)
        assert proc.stdout is not None
        for line in proc.stdout:
            log.write(line)
            if line.startswith("rendered ") and on_view is not None:
                on_view(1)
        rc = proc.wait()
    if rc != 0:
        tail = "".join(log_path.read_text().splitlines(keepends=True)[-15:])
        raise RuntimeError(f"the Cycles worker failed (exit status {rc}); log {log_path}:\n{tail}")
    for r in job["renders"]:
        if not Path(r["output"]).is_file():
            raise RuntimeError(f"the Cycles worker wrote no {r['output']} (log {log_path})")


# --------------------------------------------------------------------------------------------
# Reading the worker's multilayer EXRs
# --------------------------------------------------------------------------------------------
def read_passes(path: str | Path) -> dict[str, np.ndarray]:
    """Passes of a Cycles multilayer EXR (one part per pass in Blender 5) as float32 arrays keyed
    by pass name: {'Combined': (H,W,4), 'Normal': (H,W,3), 'Material Index': (H,W),
    and one AOV per BRDF input: a colour's (H,W,3 or 4), a scalar's (H,W), ...}."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "Cycles render missing")
    groups: dict[str, dict[str, np.ndarray]] = {}
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            for part in f.parts:
                for full, ch in part.channels.items():
                    pass_name, _, comp = full.rpartition(".")
                    pass_name = pass_name.split(".", 1)[-1] if "." in pass_name else pass_name  # drop the layer
                    if pass_name:
                        groups.setdefault(pass_name, {})[comp] = np.asarray(ch.pixels, dtype=np.float32)
    except Exception as exc:
        raise InputError(path, f"cannot read Cycles render ({type(exc).__name__}: {exc})") from exc
    out = {}
    for name, comps in groups.items():
        for order in ("RGBA", "RGB", "XYZ", "X", "V", "Z"):
            if set(order) == set(comps):
                break
        else:
            order = sorted(comps)
        arrs = [comps[c] for c in order]
        out[name] = arrs[0] if len(arrs) == 1 else np.stack(arrs, -1)
    return out


def gt_maps(passes: dict[str, np.ndarray], n_materials: int) -> dict[str, np.ndarray]:
    """GT maps in synthetic.render_gt's format from one render's passes.

    Coverage-weighted AOVs are divided by the coverage (the Mitsuba generator averages over the
    rays that hit); the material id is the material index pass where the coverage is at least
    one half, 0 elsewhere."""
    missing = [p for p in ("Combined", "Normal", INDEX_PASS, *brdf.NAMES) if p not in passes]
    if missing:
        raise InputError(None, f"Cycles render lacks the passes {missing} (found {sorted(passes)})")
    alpha = np.clip(passes["Combined"][..., 3].astype(np.float64), 0.0, 1.0)
    covered = alpha > 1e-6
    denom = np.where(covered, alpha, 1.0)

    def per_cov(x):
        x = np.asarray(x, dtype=np.float64)
        d = denom if x.ndim == 2 else denom[..., None]
        c = covered if x.ndim == 2 else covered[..., None]
        return np.where(c, x / d, 0.0)

    maps = {i.name: np.clip(per_cov(passes[i.name][..., :3] if i.colour else passes[i.name]), i.low, i.high)
            .astype(np.float32) for i in brdf.INPUTS}
    normal = passes["Normal"][..., :3].astype(np.float64)
    norm = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(norm > 1e-12, normal / np.maximum(norm, 1e-12), 0.0)
    ids = np.rint(passes[INDEX_PASS]).astype(np.int64)
    if ids.min() < 0 or ids.max() > n_materials:
        raise InputError(None, f"material index pass holds ids outside 0..{n_materials}")
    material = np.where(alpha >= 0.5, ids, 0).astype(np.uint8)
    return {**maps, "normal": normal.astype(np.float32), "material": material, "alpha": alpha.astype(np.float32)}


# --------------------------------------------------------------------------------------------
# The whole scene
# --------------------------------------------------------------------------------------------
def _bpy_version(python: Path) -> str | None:
    d = bpy_dir(python)
    if d is None:
        return None
    infos = sorted(d.parent.glob("bpy-*.dist-info"))
    return infos[-1].name[len("bpy-"):-len(".dist-info")] if infos else None


PROBE_NOTE = "negative texels (compression noise, > -0.003) clamped to 0"


def _render_list(out: Path, work: Path, cams: synthetic.SceneCameras, relights: list[dict]) -> list[dict]:
    """The worker's renders: train and test views under envmaps/train.exr, test views under each
    held-aside envmap, each into work/[<env>/]<id>.exr."""
    renders = []
    train_env = DatasetDir(out).envmap(DatasetDir.TRAIN_ENVMAP).resolve()
    for cam in cams.train + cams.test:
        renders.append({"camera": cam.name, "envmap": train_env, "output": (work / f"{cam.name}.exr").resolve()})
    for rl in relights:
        (work / rl["name"]).mkdir(parents=True, exist_ok=True)
        for cam in cams.test:
            renders.append({"camera": cam.name, "envmap": (out / rl["file"]).resolve(),
                            "output": (work / rl["name"] / f"{cam.name}.exr").resolve()})
    return renders


def _write_dataset_images(out: Path, work: Path, spec: dict, cams: synthetic.SceneCameras,
                          relights: list[dict]) -> None:
    """The worker's multilayer EXRs as the dataset layout: images/, gt/ (test views), relit/."""
    dataset = DatasetDir(out)
    n_mat = len(spec["materials"])
    test_names = {c.name for c in cams.test}
    for cam in cams.train + cams.test:
        passes = read_passes(work / f"{cam.name}.exr")
        dataset.write_view(cam.name, passes["Combined"])
        if cam.name in test_names:
            dataset.write_gt(cam.name, gt_maps(passes, n_mat))
    for rl in relights:
        dataset.relit_dir(rl["name"]).mkdir(parents=True, exist_ok=True)
        for cam in cams.test:
            passes = read_passes(work / rl["name"] / f"{cam.name}.exr")
            dataset.write_view(cam.name, passes["Combined"], rl["name"])


def make_scene_cycles(name: str, out_dir, resolution: int | None = None, n_train: int | None = None,
                      n_test: int | None = None, spp: int | None = None, seed: int = 0,
                      denoise: bool = False, threads: int = 0, keep_raw: bool = False,
                      probes: bool = True) -> Path:
    """Render the bundled scene `name` with Cycles into out_dir, in synthetic.make_scene's layout.

    None takes the scene's default for resolution and view counts; spp defaults to DEFAULT_SPP
    (Cycles' samples, denoiser off unless denoise=True). probes=False leaves out Blender's eight
    studio-light relighting probes."""
    from vq_mitsuba import messages

    synthetic.check_seed(seed)
    python = check_environment()
    init_mitsuba()
    t_start = time.time()
    spec = synthetic.load_scene_spec(name)
    if spec.get("lamps"):
        raise InputError(None, f"scene '{name}' has point lamps, which the Cycles renderer does not place: "
                               "render it with --renderer mitsuba")
    res = int(resolution or spec.get("resolution", 128))
    n_train = int(spec.get("n_train", 64) if n_train is None else n_train)
    n_test = int(spec.get("n_test", 16) if n_test is None else n_test)
    spp = int(spp or DEFAULT_SPP)
    if res < 1 or n_train < 1 or n_test < 1 or spp < 1:
        raise InputError(None, "resolution, view counts and spp must be positive")
    synthetic.check_resolution((res, res))
    dataset = DatasetDir(out_dir)
    out = dataset.prepare(DatasetDir.SUBDIRS + (WORK_DIR,))
    work = dataset.cycles_work_dir

    # Geometry, cameras and lighting as synthetic.make_scene writes them: Blender world for mesh.ply
    # and Cycles, Mitsuba world for the XML; Cycles reads the dataset's copies of the envmaps.
    geometry = synthetic.write_geometry(spec, out)
    cams = synthetic.write_cameras(out, spec, geometry, n_train, n_test, res, spp, seed)
    env_train_name, _, relights = synthetic.write_envmaps(out, spec, blender_probes(python) if probes else {},
                                                          probe_note=PROBE_NOTE)

    renders = _render_list(out, work, cams, relights)
    job = build_job(spec, geometry.shapes, cams.train + cams.test, renders, spp, seed=seed, denoise=denoise,
                    threads=threads)
    bar = messages.progress(total=len(renders), desc=f"make-scene {name} (cycles)", unit="view")
    t_render = time.time()
    try:
        run_worker(job, work / DatasetDir.CYCLES_JOB, on_view=bar.update, python=python)
    finally:
        bar.close()
    t_rendered = time.time()
    _write_dataset_images(out, work, spec, cams, relights)
    if not keep_raw:
        shutil.rmtree(work, ignore_errors=True)
    t_end = time.time()

    meta = {
        "name": name,
        "description": spec.get("description", ""),
        "renderer": "cycles",
        "resolution": [res, res],
        "n_train": n_train,
        "n_test": n_test,
        "spp": spp,
        "seed": seed,
        "cycles": {"device": "CPU", "max_bounces": MAX_BOUNCES, "denoiser": "OpenImageDenoise" if denoise else None,
                   "adaptive_sampling": False, "clamping": None, "pixel_filter": "box, 1 px",
                   "bsdf": "Principled BSDF, GGX (single scatter), IOR 1.5, Specular IOR Level 0.5",
                   "view_transform": "Standard", "film_transparent": True,
                   "material_id": "material index pass where coverage >= 0.5, else 0"},
        **synthetic.scene_description(spec, geometry.verts, geometry.shape_info, env_train_name, relights,
                                      synthetic.R_BLENDER_FROM_MITSUBA, geometry.center, geometry.radius, cams.dist,
                                      envmap_convention="Cycles Environment Texture with no mapping in Blender "
                                                        "world, identity to_world in the XML's Mitsuba world"),
        "render_seconds": round(t_rendered - t_render, 2),
        "total_seconds": round(t_end - t_start, 2),
        "versions": {"bpy": _bpy_version(python), "python_cycles": str(python), "numpy": np.__version__,
                     "vq_mitsuba": _pkg_version()},
    }
    dataset.write_info(meta)
    return out


def _pkg_version() -> str:
    from vq_mitsuba import __version__

    return __version__
