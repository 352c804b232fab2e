"""Command line: `vq-mitsuba fit | geometry | render | eval | make-scene` (thin: parses, then calls the library)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import InputError


def _run_dir(args, command: str) -> Path:
    """RUN_DIR of a command that reads a CAPTURE: -o, else runs/<name of the capture's folder>."""
    if args.capture is None:
        raise InputError(None, f"{command} needs a CAPTURE (scene XML, transforms json, or its folder)")
    return Path(args.output) if args.output else Path("runs") / Path(args.capture).resolve().parent.name


def _cmd_fit(args) -> int:
    from .config import describe, load_config
    from .fit import fit

    if args.help_config:
        print("Config keys (set them in a YAML file or with --set section.key=value):")
        print("\n".join(describe()))
        return 0
    run_dir = _run_dir(args, "fit")
    base = None
    if args.resume and (run_dir / "config.yaml").is_file():
        import yaml

        base = yaml.safe_load((run_dir / "config.yaml").read_text())
    neus_sets = [s for s in args.set if s.strip().startswith("neus.")]
    cfg = load_config(args.config, [s for s in args.set if s not in neus_sets], base=base)
    mesh_path = args.mesh
    if args.geometry == "neus" and args.mesh is not None:
        raise InputError(args.mesh, "--mesh gives known geometry but --geometry neus asks to reconstruct it; drop one")
    if args.geometry != "given" and args.mesh is None:
        from .geometry.pipeline import capture_has_geometry, ensure_geometry

        if args.geometry == "neus" or not capture_has_geometry(args.capture):
            if (run_dir / "checkpoint.pt").exists() and not args.resume:
                raise InputError(run_dir, "already holds a fitted run: pass --resume to continue it, or choose another -o")
            reused = args.resume and (run_dir / "mesh.ply").is_file()
            mesh_path = ensure_geometry(args.capture, run_dir, neus_sets, config_file=args.config,
                                        resume=args.resume, progress=not args.quiet)
            print(f"geometry: {'reusing' if reused else 'reconstructed with NeuS:'} {mesh_path}")
    summary = fit(args.capture, run_dir, cfg, mesh_path=mesh_path, resume=args.resume, progress=not args.quiet)
    print(f"fitted {summary['iterations']} iterations in {summary['seconds']:.1f} s "
          f"({summary['iterations_per_s']:.1f} it/s); results in {run_dir}/")
    return 0


def _cmd_geometry(args) -> int:
    from .geometry.pipeline import run_geometry

    if args.help_config:
        from .geometry.config import describe

        print("NeuS config keys (set them with --set neus.key=value, or a `neus:` section of --config):")
        print("\n".join(describe()))
        return 0
    run_dir = _run_dir(args, "geometry")
    info = run_geometry(args.capture, run_dir, args.set, config_file=args.config, resume=args.resume,
                        progress=not args.quiet, gt_mesh=args.gt_mesh)
    s = info["seconds"]
    print(f"NeuS: {info['iterations']} iterations in {s['train']:.1f} s (+{s['setup_and_hull']:.1f} s visual hull, "
          f"{s['mesh_export']:.1f} s mesh export); mesh with {info['mesh']['faces']} faces in {run_dir}/mesh.ply")
    if "metrics" in info:
        m = info["metrics"]
        print(f"against {args.gt_mesh}: Chamfer {100 * m['chamfer_rel']:.3f}% of the bounding-box diagonal, "
              f"normal consistency {m['normal_consistency']:.4f}, shading normals off by "
              f"{m['shading_normal_deg_median']:.2f} degrees (median)")
    return 0


def _cmd_render(args) -> int:
    from .render import render_run

    out = render_run(args.run_dir, args.cameras, args.output, envmap_path=args.envmap,
                     env_rotate_deg=args.env_rotate, exposure_ev=args.exposure, spp=args.spp,
                     progress=not args.quiet)
    print(f"rendered views in {out}/")
    return 0


def _cmd_eval(args) -> int:
    from .evaluate import evaluate, format_table

    metrics = evaluate(args.run_dir, args.gt, spp=args.spp, scale_method=args.scale,
                       progress=not args.quiet, output=args.output, meanshift_bandwidths=args.meanshift)
    print(format_table(metrics))
    out = args.output or str(Path(args.run_dir) / "metrics.json")
    print(f"metrics written to {out}")
    return 0


def _cmd_make_scene(args) -> int:
    from . import synthetic

    if args.list or args.name is None:
        print("bundled scenes: " + ", ".join(synthetic.SCENES))
        return 0
    if args.name not in synthetic.SCENES:
        raise InputError(None, f"unknown scene '{args.name}' (bundled: {', '.join(synthetic.SCENES)})")
    out = Path(args.output) if args.output else Path("data") / args.name
    kwargs = {k: v for k, v in (("resolution", args.resolution), ("spp", args.spp), ("n_train", args.n_train),
                                ("n_test", args.n_test)) if v is not None}
    if args.renderer == "cycles":
        from . import cycles

        cycles.check_environment()  # before any work: names the missing interpreter and `make cycles`
        cycles.make_scene_cycles(args.name, out, seed=args.seed, **kwargs)
    else:
        synthetic.make_scene(args.name, out, seed=args.seed, **kwargs)
    print(f"scene '{args.name}' rendered with {args.renderer} to {out}/ "
          "(scene.xml, transforms_train.json, transforms_test.json, gt/, relit/)")
    return 0


def _bandwidths(text: str) -> tuple[float, ...]:
    if text.strip().lower() in ("", "none", "off"):
        return ()
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a comma-separated list of numbers") from None
    if any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError("bandwidths must be positive")
    return values


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vq-mitsuba",
        description="Neural reflectance decomposition (VQ-NeRF) on Mitsuba 3: fit materials and lighting "
                    "to posed images, then render novel views, material maps and relighting.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    f = sub.add_parser("fit", help="fit materials (and lighting, if unknown) to a capture",
                       description="Fit the continuous material branch and the environment map to a capture "
                                   "with known geometry. Writes RUN_DIR (config.yaml, checkpoint.pt, mesh.ply, "
                                   "envmap.exr, loss.png, fit.json).")
    f.add_argument("capture", nargs="?", help="Mitsuba scene XML (sensors + images/<id>.exr|png), a "
                                              "transforms_*.json (NeRF-synthetic), or the folder holding one")
    f.add_argument("-o", "--output", help="run directory (default: runs/<capture folder name>)")
    f.add_argument("--config", help="YAML preset, e.g. configs/demo.yaml (see --help-config)")
    f.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override one config key, e.g. --set train.iterations=500 (repeatable)")
    f.add_argument("--mesh", help="known geometry (PLY/OBJ) for a NeRF-synthetic capture")
    f.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    f.add_argument("--geometry", choices=["auto", "neus", "given"], default="auto",
                   help="auto (default): the capture's shapes / mesh.ply or --mesh when there are any, otherwise "
                        "reconstruct with NeuS first (RUN_DIR/mesh.ply, reused on --resume); neus: always "
                        "reconstruct from the images (needs alpha masks); given: never reconstruct")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.add_argument("--help-config", action="store_true", help="list every config key with its default and meaning")
    f.set_defaults(func=_cmd_fit)

    g = sub.add_parser("geometry", help="reconstruct a mesh from posed images with alpha masks (NeuS)",
                       description="NeuS on the capture's images and masks, then marching cubes and mesh clean-up. "
                                   "Writes RUN_DIR/mesh.ply, geometry.json (timings, settings), geometry_loss.png and "
                                   "the NeuS checkpoint neus.pt. Known geometry in the capture is ignored.")
    g.add_argument("capture", nargs="?", help="Mitsuba scene XML, a transforms_*.json, or the folder holding one")
    g.add_argument("-o", "--output", help="run directory (default: runs/<capture folder name>)")
    g.add_argument("--config", help="YAML file whose `neus:` section sets NeuS keys")
    g.add_argument("--set", action="append", default=[], metavar="neus.KEY=VALUE",
                   help="override one NeuS key, e.g. --set neus.iterations=3000 (repeatable)")
    g.add_argument("--gt-mesh", help="score the mesh against this ground-truth mesh (Chamfer, normal consistency)")
    g.add_argument("--resume", action="store_true", help="continue from RUN_DIR/neus.pt")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.add_argument("--help-config", action="store_true", help="list every NeuS config key with its default")
    g.set_defaults(func=_cmd_geometry)

    r = sub.add_parser("render", help="render novel views, material maps and relighting of a fitted run",
                       description="For each camera NAME writes NAME_rgb.exr/.png, NAME_basecolor.exr, "
                                   "NAME_metallic.exr, NAME_roughness.exr, NAME_normal.exr, NAME_alpha.png.")
    r.add_argument("run_dir", help="a run directory written by `vq-mitsuba fit`")
    r.add_argument("--cameras", required=True, help="transforms_*.json or Mitsuba XML with sensors")
    r.add_argument("--envmap", help="relight with this lat-long HDR image (EXR), in the capture's world "
                                    "convention (Blender's for NeRF/Blender captures)")
    r.add_argument("--env-rotate", type=float, default=0.0, metavar="DEG",
                   help="rotate the lighting about the up axis by DEG degrees")
    r.add_argument("--exposure", type=float, default=0.0, metavar="EV", help="scale the lighting by 2^EV")
    r.add_argument("--spp", type=int, help="samples per pixel (default: render.spp of the run's config)")
    r.add_argument("-o", "--output", help="output folder (default: RUN_DIR/renders)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_render)

    e = sub.add_parser("eval", help="score a fitted run against a synthetic dataset's ground truth",
                       description="Render the dataset's test views (transforms_test.json) and compare inside "
                                   "the ground-truth foreground: novel-view PSNR/SSIM, basecolor PSNR/SSIM after "
                                   "per-channel scale alignment, metallic/roughness PSNR, and relighting PSNR/SSIM "
                                   "under each held-aside envmap (albedo-scale and image-scale variants).")
    e.add_argument("run_dir", help="a run directory written by `vq-mitsuba fit`")
    e.add_argument("--gt", required=True, metavar="DATASET",
                   help="dataset folder written by `vq-mitsuba make-scene` (scene.json, transforms_test.json, "
                        "images/, gt/, relit/, envmaps/)")
    e.add_argument("-o", "--output", help="metrics JSON path (default: RUN_DIR/metrics.json)")
    e.add_argument("--spp", type=int, help="render samples per pixel (default: render.spp of the run's config)")
    e.add_argument("--scale", choices=["lstsq", "median"], default="lstsq",
                   help="basecolor scale alignment: lstsq (NeRFactor) or median (TensoIR)")
    e.add_argument("--meanshift", type=_bandwidths, default=(0.2, 0.3, 0.5), metavar="BW,BW,...",
                   help="bandwidths of the MeanShift segmentation baseline on the continuous branch's "
                        "BRDF maps (default 0.2,0.3,0.5; 'none' skips it); needs ground-truth material ids")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=_cmd_eval)

    m = sub.add_parser("make-scene", help="render a bundled synthetic scene with ground truth",
                       description="Render a bundled scene with Mitsuba's path tracer (or Blender Cycles with "
                                   "--renderer cycles): training and test views in both capture formats, "
                                   "ground-truth maps and relit test views.")
    m.add_argument("name", nargs="?", help="scene name (see --list)")
    m.add_argument("-o", "--output", help="output folder (default: data/NAME)")
    m.add_argument("--resolution", type=int, help="image width and height in pixels (default per scene)")
    m.add_argument("--spp", type=int, help="path-tracing samples per pixel (default: the scene's for mitsuba, "
                                           "128 for cycles)")
    m.add_argument("--renderer", choices=["mitsuba", "cycles"], default="mitsuba",
                   help="mitsuba (default) or cycles: Blender Cycles through bpy in .venv-cycles (`make cycles`); "
                        "same output layout, plus relit views under Blender's eight studio-light probes")
    m.add_argument("--n-train", type=int, help="number of training views")
    m.add_argument("--n-test", type=int, help="number of test views")
    m.add_argument("--seed", type=int, default=0, help="random seed")
    m.add_argument("--list", action="store_true", help="list the bundled scenes")
    m.set_defaults(func=_cmd_make_scene)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; the last checkpoint is kept (continue with `vq-mitsuba fit ... --resume`)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
