"""`vq-mitsuba render`, run from here: a finished run's views under the fitted or given lightings,
into an output folder that also gets `render.json` (the run, cameras and lighting used).

Reads the run through `run.run_dir` only and imports no training module.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Sequence

from vq_mitsuba.config import CaptureConfig, load_config
from vq_mitsuba.data.captures import load_cameras
from vq_mitsuba.data.envmaps import check_peak, load_envmap
from vq_mitsuba.data.names import safe_name
from vq_mitsuba.errors import InputError
from vq_mitsuba.render import views
from vq_mitsuba.run.outputs import RENDER_MARKER, check_output_folder
from vq_mitsuba.run.run_dir import RunDir, check_writable, write_json


def lighting_names(envmap_paths: Sequence[str | Path]) -> list[str]:
    """The folder name of each lighting (its file's safe stem); two lightings may not share one,
    since their views would go to the same folder."""
    names = [safe_name(Path(p).stem) for p in envmap_paths]
    if len(set(names)) < len(names):
        raise InputError(None, f"--envmap: two lightings share a file name ({', '.join(names)}); their "
                               "views would go to the same folder")
    return names


@contextmanager
def new_folder(path: Path):
    """Make the output folder `path`; if the command then fails, remove it again when it was new
    and is still empty (a refusal leaves no empty folder behind)."""
    new = not path.exists()
    path.mkdir(parents=True, exist_ok=True)
    try:
        yield path
    except BaseException:
        if new and not any(path.iterdir()):
            path.rmdir()
        raise


def render_run(run_dir: str | Path, cameras_path: str | Path, out_dir: str | Path | None = None,
               envmap_paths: Sequence[str | Path] = (), size: CaptureConfig | None = None,
               env_rotate_deg: float = 0.0, exposure_ev: float = 0.0, spp: int | None = None,
               keep_lamps: bool = False) -> Path:
    """Render the run's views for every camera of `cameras_path` into `out_dir` (default
    RUN_DIR/renders): the first lighting (the fitted envmap when `envmap_paths` is empty) into it,
    each further one into OUT/<its file name>; then write OUT/render.json. Every input is checked
    before any rendering. `keep_lamps`: the run's fitted lamps light the relit views too. `size` is
    the capture section whose downscale and max_size shrink the cameras' images. Returns the output
    folder."""
    size = size if size is not None else load_config(None).capture
    run = RunDir(run_dir)
    out = Path(out_dir) if out_dir is not None else run.dir / RunDir.RENDERS
    check_output_folder(out, "render", "render")
    check_writable(out)
    fitted = run.load()
    cameras, world, _ = load_cameras(cameras_path, size)
    envmaps = [load_envmap(p, exposure_ev) for p in envmap_paths]  # each checked at this exposure, by name
    if not envmap_paths:
        check_peak(fitted.envmap, run.dir / RunDir.ENVMAP, exposure_ev)
    names = lighting_names(envmap_paths)
    lamps = fitted.lamps if keep_lamps or views.own_lighting(envmaps[0] if envmaps else None, env_rotate_deg,
                                                               exposure_ev) else None
    with new_folder(out):
        views.render_views(fitted, cameras, world, out, envmap=envmaps[0] if envmaps else None,
                           env_rotate_deg=env_rotate_deg, exposure_ev=exposure_ev, spp=spp,
                           more_envmaps=list(zip(names[1:], envmaps[1:])), keep_lamps=keep_lamps)
        write_json(out / RENDER_MARKER, {
            "run": str(run.dir.resolve()), "cameras": str(Path(cameras_path).resolve()),
            "envmap": str(Path(envmap_paths[0]).resolve()) if envmap_paths else "fitted",
            "more_envmaps": {n: str(Path(p).resolve()) for n, p in zip(names[1:], envmap_paths[1:])},
            "env_rotate_deg": env_rotate_deg, "exposure_ev": exposure_ev, "views": [c.name for c in cameras],
            "lamps": 0 if lamps is None else len(lamps.position),
            "downscale": size.downscale, "max_size": size.max_size,
        })
    return out
