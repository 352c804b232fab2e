"""`vq-mitsuba render`: a finished run's views (`vq_mitsuba.render.render_run.render_run`); no training
module is imported."""

from __future__ import annotations

from vq_mitsuba.cli.common import capture_flags, finite, output_option, positive_int, refuse_file_output


def add_parser(sub, shared) -> None:
    r = sub.add_parser(
        "render", parents=[shared["threads"], shared["device"], output_option("output folder (default: RUN_DIR/renders)"),
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
    r.add_argument("--keep-lamps", action="store_true",
                   help="light views under another --envmap with the run's fitted lamps too (default: the envmap alone)")
    r.add_argument("--spp", type=positive_int, help="samples per pixel (default: render.spp of the run's config)")
    r.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.config import load_config
    from vq_mitsuba.render.render_run import render_run

    refuse_file_output(args.output)
    size = load_config(None, capture_flags(args)).capture  # --downscale, --max-size
    out = render_run(args.run_dir, args.cameras, args.output, args.envmap, size, env_rotate_deg=args.env_rotate,
                     exposure_ev=args.exposure, spp=args.spp, keep_lamps=args.keep_lamps)
    print(f"rendered views in {out}/")
    return 0
