"""`vq-mitsuba render`: a finished run's views through RunDir (`vq_mitsuba.render.views.render_views`);
no training module is imported."""

from __future__ import annotations

from pathlib import Path

from vq_mitsuba.cli.common import capture_flags, finite, new_folder, output_option, positive_int, refuse_file_output
from vq_mitsuba.errors import InputError


def add_parser(sub, shared) -> None:
    r = sub.add_parser(
        "render", parents=[shared["threads"], output_option("output folder (default: RUN_DIR/renders)"),
                           shared["quiet"], shared["size"]],
        help="render novel views, material maps and relighting of a fitted run",
        description="For each camera NAME writes NAME_rgb.exr/.png, NAME_basecolor.exr, NAME_metallic.exr, "
                    "NAME_roughness.exr, NAME_normal.exr, NAME_alpha.png, and with the discrete branch "
                    "NAME_material.png (ids) and NAME_segmentation.png (overlay). An envmap is a lat-long HDR "
                    "image in the capture's world convention (Blender's for NeRF/Blender captures). With several "
                    "--envmap, the first lighting's views go to OUT and each further one's to OUT/<file name>, "
                    "rendered in one pass. --downscale / --max-size shrink the cameras' images (a 1600x1200 "
                    "photo capture rendered smaller). OUT/render.json records the run, cameras and lighting used.")
    r.add_argument("run_dir", help="a run directory written by `vq-mitsuba fit`")
    r.add_argument("--cameras", required=True, help="any capture (its cameras only): transforms json, XML, ...")
    r.add_argument("--envmap", action="append", default=[],
                   help="relight with this lat-long HDR image (EXR or Radiance .hdr); repeatable")
    r.add_argument("--env-rotate", type=finite(1e6), default=0.0, metavar="DEG",
                   help="rotate the lighting about the up axis by DEG degrees")
    r.add_argument("--exposure", type=finite(64), default=0.0, metavar="EV", help="scale the lighting by 2^EV")
    r.add_argument("--spp", type=positive_int, help="samples per pixel (default: render.spp of the run's config)")
    r.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.data.envmaps import load_envmap
    from vq_mitsuba.data.names import safe_name
    from vq_mitsuba.run.outputs import RENDER_MARKER, check_output_folder
    from vq_mitsuba.run.run_dir import RunDir, check_writable, write_json
    from vq_mitsuba.render.views import render_views

    refuse_file_output(args.output)
    run = RunDir(args.run_dir)
    out = Path(args.output) if args.output else run.dir / RunDir.RENDERS
    check_output_folder(out, "render", "render")
    check_writable(out)
    fitted = run.load()
    size = load_config(None, capture_flags(args)).capture  # --downscale, --max-size
    cameras, world, _ = load_cameras(args.cameras, size)  # input checks before any rendering
    envmaps = [load_envmap(p) for p in args.envmap]
    names = [safe_name(Path(p).stem) for p in args.envmap]  # folder names of the further lightings
    if len(set(names)) < len(names):
        raise InputError(None, f"--envmap: two lightings share a file name ({', '.join(names)}); their "
                               "views would go to the same folder")
    with new_folder(out):
        render_views(fitted, cameras, world, out, envmap=envmaps[0] if envmaps else None,
                     env_rotate_deg=args.env_rotate, exposure_ev=args.exposure, spp=args.spp, progress=not args.quiet,
                     more_envmaps=list(zip(names[1:], envmaps[1:])))
        write_json(out / RENDER_MARKER, {
            "run": str(run.dir.resolve()), "cameras": str(Path(args.cameras).resolve()),
            "envmap": str(Path(args.envmap[0]).resolve()) if args.envmap else "fitted",
            "more_envmaps": {n: str(Path(p).resolve()) for n, p in zip(names[1:], args.envmap[1:])},
            "env_rotate_deg": args.env_rotate, "exposure_ev": args.exposure, "views": [c.name for c in cameras],
            "downscale": size.downscale, "max_size": size.max_size,
        })
    print(f"rendered views in {out}/")
    return 0
