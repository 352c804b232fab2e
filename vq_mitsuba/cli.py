"""Command line: `vq-mitsuba fit | geometry | pose | render | edit | export | ui | eval | make-scene | batch`.

Thin: one parser built from shared parent parsers (each option defined once), then one library
call per command (`fit` is `vq_mitsuba.engine.pipeline.fit_capture`) and its report."""

from __future__ import annotations

import argparse
import sys
import warnings
from contextlib import contextmanager
from pathlib import Path

from vq_mitsuba.errors import InputError, UserError


def _run_dir(args, command: str) -> Path:
    """RUN_DIR of a command that reads a CAPTURE: -o, else runs/<name of the capture's folder> (of
    the folder itself when CAPTURE is one, e.g. of photos; a video's name)."""
    from vq_mitsuba.data.unposed import capture_name

    if args.capture is None:
        raise InputError(None, f"{command} needs a CAPTURE (scene XML, transforms json, or its folder)")
    return Path(args.output) if args.output else Path("runs") / capture_name(args.capture)


def _help_config() -> int:
    from vq_mitsuba.config import describe, presets

    print("Config keys (set them in a preset, a YAML file, or with --set section.key=value):")
    print("\n".join(describe()))
    print(f"Presets (--preset NAME, configs/NAME.yaml): {', '.join(presets())}")
    return 0


def _config(args, run_dir: Path | None = None):
    """Defaults <- the run's saved config (on --resume) <- --preset <- --config <- --set."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.run.run_dir import RunDir

    base = RunDir(run_dir).saved_config() if (args.resume and run_dir is not None) else None
    return load_config(args.config, _capture_flags(args) + list(args.set), base=base, preset=args.preset)


def _capture_flags(args) -> list[str]:
    """The capture options given (--downscale, --max-size, ...) as config overrides `capture.KEY=VALUE`,
    each checked alone, so that an error names the option, not --set."""
    from vq_mitsuba.config import load_config

    flags = []
    for key in ("downscale", "max_size", "background_color", "holdout"):
        value = getattr(args, key, None)
        if value is None:
            continue
        flags.append(f"capture.{key}={value}")
        try:
            load_config(None, flags[-1:])
        except InputError as exc:
            raise InputError(None, f"--{key.replace('_', '-')} {value}: {exc.message}") from None
    return flags


def _cmd_fit(args) -> int:
    from vq_mitsuba.engine.pipeline import fit_capture
    from vq_mitsuba.run.run_dir import RunDir, check_writable

    if args.help_config:
        return _help_config()
    run_dir = _run_dir(args, "fit")
    _output_folder(run_dir)
    check_writable(run_dir)
    cfg = _config(args, run_dir)  # bad keys and values fail before any work
    summary = fit_capture(args.capture, run_dir, cfg, geometry=args.geometry, mesh=args.mesh, resume=args.resume,
                          progress=not args.quiet)
    print(f"fitted {summary['iterations']} iterations in {summary['seconds']:.1f} s "
          f"({summary['iterations_per_s']:.1f} it/s); results in {run_dir}/")
    materials = RunDir(run_dir).materials()
    if materials is not None and cfg.vq.enabled:
        print(f"materials: M = {materials['num_materials']} ({run_dir}/materials.json, materials_sheet.png, "
              "materials_err.png)")
    return 0


def _cmd_geometry(args) -> int:
    from vq_mitsuba.geometry.pipeline import check_geometry_target, neus_psnr_line, run_geometry
    from vq_mitsuba.run.outputs import removed_on_refusal
    from vq_mitsuba.run.run_dir import RunDir

    if args.help_config:
        return _help_config()
    run_dir = _run_dir(args, "geometry")
    _output_folder(run_dir)
    check_geometry_target(RunDir(run_dir))
    cfg = _config(args)
    with RunDir(run_dir).lock("geometry"), removed_on_refusal(run_dir):
        info = run_geometry(args.capture, run_dir, cfg.neus, resume=args.resume, progress=not args.quiet,
                            gt_mesh=args.gt_mesh, capture_cfg=cfg.capture, pose_cfg=cfg.pose).summary
    s = info["seconds"]
    print(f"NeuS: {info['iterations']} iterations in {s['train']:.1f} s (+{s['setup_and_hull']:.1f} s visual hull, "
          f"{s['mesh_export']:.1f} s mesh export); mesh with {info['mesh']['faces']} faces in {run_dir}/mesh.ply")
    print(neus_psnr_line(info["neus_psnr"]))
    if "metrics" in info:
        m = info["metrics"]
        print(f"against {args.gt_mesh}: Chamfer {100 * m['chamfer_rel']:.3f}% of the bounding-box diagonal, "
              f"normal consistency {m['normal_consistency']:.4f}, shading normals off by "
              f"{m['shading_normal_deg_median']:.2f} degrees (median)")
    return 0


def _cmd_pose(args) -> int:
    from vq_mitsuba.geometry.poses import pose_capture
    from vq_mitsuba.run.run_dir import check_writable

    if args.help_config:
        return _help_config()
    if args.source is None:
        raise InputError(None, "pose needs a folder of photos or a video")
    if args.output is None:
        raise InputError(None, "pose writes a COLMAP capture: give it a folder with -o OUT")
    _output_folder(args.output)
    check_writable(args.output)
    cfg = _config(args)
    summary = pose_capture(args.source, args.output, cfg.pose, progress=not args.quiet)
    print(f"{summary['registered']} of {summary['images']} images posed, mean reprojection error "
          f"{summary['mean_reprojection_error_px']:.2f} px: {args.output}/ (images/, sparse/0/, pose.json); "
          f"fit it with: vq-mitsuba fit {args.output}")
    return 0


def _cmd_render(args) -> int:
    """Reads the finished run through RunDir and renders it: no training module is imported."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import load_cameras
    from vq_mitsuba.data.envmaps import load_envmap
    from vq_mitsuba.data.names import safe_name
    from vq_mitsuba.run.outputs import RENDER_MARKER, check_output_folder
    from vq_mitsuba.run.run_dir import RunDir, check_writable, write_json
    from vq_mitsuba.render.views import render_views

    _output_folder(args.output)
    run = RunDir(args.run_dir)
    out = Path(args.output) if args.output else run.dir / RunDir.RENDERS
    check_output_folder(out, "render", "render")
    check_writable(out)
    fitted = run.load()
    size = load_config(None, _capture_flags(args)).capture  # --downscale, --max-size
    cameras, world, _ = load_cameras(args.cameras, size)  # input checks before any rendering
    envmaps = [load_envmap(p) for p in args.envmap]
    names = [safe_name(Path(p).stem) for p in args.envmap]  # folder names of the further lightings
    if len(set(names)) < len(names):
        raise InputError(None, f"--envmap: two lightings share a file name ({', '.join(names)}); their "
                               "views would go to the same folder")
    with _new_folder(out):
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


def _edit_label(args) -> str:
    """The edit as the user asked for it, e.g. "--material 2 --preset gold" (stored with the edit)."""
    parts = [f"--material {k}" for k in args.material] + [f"--pick {p}" for p in args.pick]
    parts += [f"--box {b}" for b in args.box] + ([f"--preset {args.preset}"] if args.preset else [])
    parts += [f"--set {x}" for x in args.set] + [f"--scale {x}" for x in args.scale]
    return " ".join(parts + ([f"--hue-shift {args.hue_shift:g}"] if args.hue_shift is not None else []))


def _cmd_edit(args) -> int:
    from vq_mitsuba.edit import build_edit, edit_run
    from vq_mitsuba.run.outputs import check_output_folder
    from vq_mitsuba.run.run_dir import RunDir, check_writable
    from vq_mitsuba.models.edits import material_library

    if args.list_presets:
        for name, m in sorted(material_library().items()):
            print(f"{name:14s} basecolor {m['basecolor']} metallic {m['metallic']} roughness {m['roughness']}  ({m['note']})")
        return 0
    if args.output is None:
        raise InputError(None, "edit writes a new run: give it a folder with -o NEW_RUN")
    _output_folder(args.output)
    check_output_folder(args.output, "edit", "edit")
    check_writable(args.output)
    run = RunDir(args.run_dir)
    fitted = run.load()
    edit = build_edit(run, fitted, args.material, args.pick, args.box, args.set, args.scale, args.hue_shift,
                      args.preset, label=_edit_label(args))
    out = edit_run(run, args.output, edit)
    sel = edit.selection
    what = (f"material{'s' if len(sel.materials) > 1 else ''} {', '.join(map(str, sel.materials))}"
            if sel.materials else "every material") + \
        (f" inside {len(sel.boxes)} box(es)" if sel.boxes else "")
    print(f"edited {what}: {len(edit.changes)} change(s); {len(out.edits())} edit(s) in {out.dir / RunDir.EDITS}")
    print(f"render it with: vq-mitsuba render {out.dir} --cameras CAMERAS")
    return 0


def _cmd_export(args) -> int:
    from vq_mitsuba.export.formats import export_run

    _output_folder(args.output)
    summary = export_run(args.run_dir, args.format, args.output, args.texture_size, args.branch, args.envmap,
                         progress=not args.quiet)
    s = summary["seconds"]
    print(f"exported {summary['format']} ({summary['branch']} branch, {summary['texture_size']}^2 textures, "
          f"baked in {s['bake']:.1f} s) to {args.output}/: {', '.join(summary['files'])}")
    return 0


def _cmd_ui(args) -> int:
    from vq_mitsuba.ui.server import serve

    if not 0 <= args.port <= 65535:
        raise InputError(None, f"--port {args.port}: a port is 0..65535 (0: any free port)")
    if args.envmaps is not None and not Path(args.envmaps).is_dir():
        raise InputError(Path(args.envmaps), "is not a folder (--envmaps names a folder of .exr / .hdr files)")
    serve(args.run_dir, host=args.host, port=args.port, envmap_dir=args.envmaps, size=args.size)
    return 0


def _cmd_eval(args) -> int:
    from vq_mitsuba.eval.evaluate import evaluate, evaluate_holdout, format_table
    from vq_mitsuba.run.outputs import check_metrics_file
    from vq_mitsuba.run.run_dir import RunDir, check_writable

    if args.output is not None:
        check_metrics_file(args.output)
    check_writable(Path(args.output).parent if args.output else args.run_dir)
    size = {k: getattr(args, k) for k in ("downscale", "max_size") if getattr(args, k) is not None}
    _capture_flags(args)  # checked before any work
    if args.gt is not None and size:
        raise InputError(None, "--downscale and --max-size resize the held-out photos of a real capture (eval "
                               "without --gt); a synthetic dataset's ground truth is scored at its own size")
    if args.gt is None:  # a real capture: the held-out views
        metrics = evaluate_holdout(args.run_dir, spp=args.spp, progress=not args.quiet, output=args.output, **size)
        print(f"held-out views ({len(metrics['views'])}): novel view PSNR {metrics['novel_view']['psnr']:.2f} dB, "
              f"SSIM {metrics['novel_view']['ssim']:.4f} (inside the masks)")
    else:
        metrics = evaluate(args.run_dir, args.gt, spp=args.spp, scale_method=args.scale,
                           progress=not args.quiet, output=args.output, meanshift_bandwidths=args.meanshift)
        print(format_table(metrics))
    print(f"metrics written to {args.output or RunDir(args.run_dir) / RunDir.METRICS}")
    return 0


def _cmd_make_scene(args) -> int:
    from vq_mitsuba.run.outputs import check_output_folder
    from vq_mitsuba.run.run_dir import check_writable
    from vq_mitsuba.synthetic import mitsuba_scenes as synthetic

    if args.list or args.name is None:
        print("bundled scenes: " + ", ".join(synthetic.SCENES))
        return 0
    if args.name not in synthetic.SCENES:
        raise InputError(None, f"unknown scene '{args.name}' (bundled: {', '.join(synthetic.SCENES)})")
    out = Path(args.output) if args.output else Path("data") / args.name
    check_output_folder(out, "scene", "make-scene")
    check_writable(out)
    kwargs = {k: v for k, v in (("resolution", args.resolution), ("spp", args.spp), ("n_train", args.n_train),
                                ("n_test", args.n_test)) if v is not None}
    if args.renderer == "cycles":
        if args.photo_formats or isinstance(args.resolution, tuple):
            raise InputError(None, "--photo-formats and a WxH --resolution are made with --renderer mitsuba")
        from vq_mitsuba.synthetic import cycles

        cycles.check_environment()  # before any work: names the missing interpreter and `make cycles`
        cycles.make_scene_cycles(args.name, out, seed=args.seed, **kwargs)
    else:
        synthetic.make_scene(args.name, out, seed=args.seed, photo_formats=args.photo_formats, **kwargs)
    print(f"scene '{args.name}' rendered with {args.renderer} to {out}/ "
          "(scene.xml, transforms_train.json, transforms_test.json, gt/, relit/)")
    return 0


def _cmd_batch(args) -> int:
    from vq_mitsuba.batch import parse_seeds, run_batch

    if args.help_config:
        return _help_config()
    _config(args)  # bad keys and values fail before any run starts
    fit_args = [x for key in ("downscale", "max_size") if getattr(args, key) is not None
                for x in (f"--{key.replace('_', '-')}", str(getattr(args, key)))]
    fit_args += [x for item in args.set for x in ("--set", item)]
    fit_args += ["--config", str(Path(args.config).resolve())] if args.config else []
    rows = run_batch(args.captures, args.output, seeds=parse_seeds(args.seeds), presets=[args.preset],
                     fit_args=fit_args, threads=args.threads_per_run, evaluate=args.eval, address=args.address,
                     progress=not args.quiet)
    done = sum(r.get("status") == "done" for r in rows)
    for row in rows:
        if row.get("status") != "done":
            print(f"{row['run']}: {row.get('status', 'not run')}: {row.get('message', '')}", file=sys.stderr)
    print(f"{done} of {len(rows)} runs done; summary in {args.output}/summary.md and summary.csv")
    return 0 if done == len(rows) else 1


def _resolution(text: str):
    """N (an int) or WxH (a tuple)."""
    parts = text.lower().split("x")
    if len(parts) == 1:
        return _positive_int(parts[0])
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"'{text}' is neither N nor WxH")
    return _positive_int(parts[0]), _positive_int(parts[1])


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _finite(limit: float):
    """A float type accepting finite values of magnitude <= limit."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        if not abs(value) <= limit:  # also refuses nan
            raise argparse.ArgumentTypeError(f"must be a finite number within +-{limit:g}, got {text}")
        return value
    return parse


def _output_folder(path: str | None) -> None:
    """-o names a folder: refuse an existing file before any work."""
    if path is not None and Path(path).exists() and not Path(path).is_dir():
        raise InputError(path, "is a file; -o names an output folder")


@contextmanager
def _new_folder(path: Path):
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


def _parent() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(add_help=False)


def _output(help: str, metavar: str | None = None, required: bool = False) -> argparse.ArgumentParser:
    """-o, the one output option; `help` says what it names for the command and its default."""
    p = _parent()
    p.add_argument("-o", "--output", required=required, metavar=metavar, help=help)
    return p


def _shared_parents() -> dict[str, argparse.ArgumentParser]:
    """The options several commands share, each defined once (argparse parents)."""
    threads = _parent()
    threads.add_argument("--threads", type=_positive_int, metavar="N",
                         help="CPU threads for torch and Dr.Jit (default: every core this process may use)")
    quiet = _parent()
    quiet.add_argument("--quiet", action="store_true", help="no progress bar")
    config = _parent()  # the config file system: docs/configuration.md
    config.add_argument("--preset", metavar="NAME", help="apply the named preset configs/NAME.yaml (see --help-config)")
    config.add_argument("--config", metavar="FILE", help="apply a YAML config file, after --preset")
    config.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one config key, e.g. train.iterations=500 (repeatable)")
    config.add_argument("--help-config", action="store_true", help="list every config key and preset")
    size = _parent()  # how large the photos are read (config section capture): fit, geometry, render, eval
    size.add_argument("--downscale", type=_positive_int, metavar="N",
                      help="divide the photos' width and height by N (capture.downscale)")
    size.add_argument("--max-size", type=int, metavar="N",
                      help="shrink each photo as it is read to at most N pixels a side (capture.max_size)")
    # the capture, and how its images are read (config section capture)
    capture = argparse.ArgumentParser(add_help=False, parents=[size])
    capture.add_argument("capture", nargs="?", help="a scene XML, transforms json, cameras_sphere.npz, COLMAP "
                                                    "folder (or their folder), photos, a video")
    capture.add_argument("--background-color", metavar="R,G,B",
                         help="key out a plain backdrop of this sRGB colour (0..1) as the mask")
    capture.add_argument("--holdout", type=_positive_int, metavar="K",
                         help="keep every K-th view out of training, for `eval RUN_DIR` (capture.holdout)")
    resume = _parent()
    resume.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    return {"threads": threads, "quiet": quiet, "config": config, "size": size, "capture": capture, "resume": resume}


RUN_DIR_OUTPUT = "run directory (default: runs/<capture folder name>)"


def _run_parents(shared) -> list:
    """The options of the commands that write a run folder from a capture (fit, geometry)."""
    return [shared["threads"], _output(RUN_DIR_OUTPUT)] + [shared[k] for k in ("capture", "config", "resume", "quiet")]


def _add_fit(sub, shared) -> None:
    f = sub.add_parser(
        "fit", parents=_run_parents(shared), help="decompose a capture into materials and lighting (VQ-NeRF)",
        description="Fit VQ-NeRF to a capture: geometry (given, or NeuS from the images), the continuous and "
                    "discrete material branches, the lighting if unknown, and the ranked materials. Writes RUN_DIR "
                    "(docs/run_dir.md): run.json, config.yaml, checkpoint.pt, mesh.ply, envmap.exr, materials.json, "
                    "materials_err.png, materials_sheet.png, loss.png, fit.json, residual.pt. --geometry auto (the "
                    "default) uses the capture's shapes, its mesh.ply or --mesh when there are any, and otherwise "
                    "reconstructs the mesh with NeuS first (RUN_DIR/mesh.ply, reused on --resume); neus always "
                    "reconstructs it from the images (with their masks when they have any); given never does.")
    f.add_argument("--mesh", help="known geometry (PLY/OBJ) in the capture's world, for any posed capture")
    f.add_argument("--geometry", choices=["auto", "neus", "given"], default="auto",
                   help="where the mesh comes from: auto (default), neus or given (see above)")
    f.set_defaults(func=_cmd_fit)


def _add_geometry(sub, shared) -> None:
    g = sub.add_parser(
        "geometry", parents=_run_parents(shared), help="reconstruct a mesh from posed images, with or without masks (NeuS)",
        description="NeuS on the capture's images (and masks, when it has any), then marching cubes and mesh "
                    "clean-up. Writes "
                    "RUN_DIR/mesh.ply, geometry.json (timings, settings), geometry_loss.png and the NeuS "
                    "checkpoint neus.pt. Known geometry in the capture is ignored. Of the config, the `neus` and "
                    "`capture` sections apply (e.g. --set neus.iterations=3000).")
    g.add_argument("--gt-mesh", help="score the mesh against this ground-truth mesh (Chamfer, normal consistency)")
    g.set_defaults(func=_cmd_geometry)


def _add_pose(sub, shared) -> None:
    p = sub.add_parser(
        "pose", parents=[shared["threads"], _output("the posed capture to write", metavar="OUT"),
                         shared["config"], shared["quiet"]],
        help="find the camera poses of photos or a video (SfM): a COLMAP capture to fit",
        description="Structure from motion with COLMAP (pycolmap): SIFT features, matching, incremental mapping "
                    "with one camera for all images. SOURCE is a folder of photos (JPEG / PNG, one size; EXIF "
                    "orientation applied) or a video (.mp4 .mov .avi .mkv .webm: the sharpest frame of each of "
                    "pose.frames equal time windows). Writes OUT/images/, OUT/sparse/0/ (the model that places the "
                    "most images) and OUT/pose.json (images placed, mean reprojection error, timings); refused "
                    "when fewer than pose.min_registered of the images (and at least 3) are placed. Run again on "
                    "the same inputs, OUT is reused. `fit` does this on its own for photos or a video (RUN_DIR/pose/).")
    p.add_argument("source", nargs="?", help="a folder of photos or a video file")
    p.set_defaults(func=_cmd_pose, resume=False)


def _add_render(sub, shared) -> None:
    r = sub.add_parser(
        "render", parents=[shared["threads"], _output("output folder (default: RUN_DIR/renders)"), shared["quiet"],
                           shared["size"]],
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
    r.add_argument("--env-rotate", type=_finite(1e6), default=0.0, metavar="DEG",
                   help="rotate the lighting about the up axis by DEG degrees")
    r.add_argument("--exposure", type=_finite(64), default=0.0, metavar="EV", help="scale the lighting by 2^EV")
    r.add_argument("--spp", type=_positive_int, help="samples per pixel (default: render.spp of the run's config)")
    r.set_defaults(func=_cmd_render)


def _add_edit(sub, shared) -> None:
    d = sub.add_parser(
        "edit", parents=[shared["threads"], _output("the edited run to write", metavar="NEW_RUN")],
        help="select materials of a fitted run and change them (writes a new run)",
        description="Select surface points by ranked material, by the material under a pixel, and / or by a "
                    "world-space box (material and box selections intersect), and change their BRDF. Writes "
                    "NEW_RUN with run.json naming RUN_DIR's fitted run and edits.json, the edit list (RUN_DIR's "
                    "edits plus this one); render, export and eval of NEW_RUN show the edit. --set takes "
                    "basecolor=R,G,B (linear, 0..1) or basecolor=#RRGGBB (sRGB), metallic=V or roughness=V; "
                    "--scale multiplies basecolor, metallic or roughness by F, keeping the texture (clamped to 0..1).")
    d.add_argument("run_dir", nargs="?", help="a fitted (or already edited) run directory")
    d.add_argument("--material", type=int, action="append", default=[], metavar="K",
                   help="select the K-th ranked material (materials.json; repeatable)")
    d.add_argument("--pick", action="append", default=[], metavar="VIEW:X,Y",
                   help="select the material under pixel X,Y of the capture's (or its test cameras') view VIEW")
    d.add_argument("--box", action="append", default=[], metavar="x0,y0,z0,x1,y1,z1",
                   help="keep only points inside this world-space box (the capture's coordinates; repeatable)")
    d.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="set basecolor, metallic or roughness of the selection (see above)")
    d.add_argument("--scale", action="append", default=[], metavar="KEY=F",
                   help="multiply basecolor, metallic or roughness by F (see above)")
    d.add_argument("--hue-shift", type=_finite(1e6), metavar="DEG", help="rotate the basecolor's hue by DEG degrees")
    d.add_argument("--preset", metavar="NAME", help="a named material of the library (see --list-presets)")
    d.add_argument("--list-presets", action="store_true", help="list the library's materials")
    d.set_defaults(func=_cmd_edit)


def _add_export(sub, shared) -> None:
    x = sub.add_parser(
        "export", parents=[shared["threads"], _output("output folder", metavar="OUT", required=True), shared["quiet"]],
        help="take a fitted or edited run to Blender, three.js or Mitsuba",
        description="UV-unwrap the mesh, bake basecolor, metallic, roughness and the material ids into textures, "
                    "and write a glTF binary (.glb, metallic-roughness PBR), OBJ+MTL (PBR keys) or a Mitsuba scene "
                    "XML (mesh, principled with textures, envmap, the capture's cameras). The lighting goes beside "
                    "it as envmap.exr and envmap.hdr.")
    x.add_argument("run_dir", help="a fitted or edited run directory")
    x.add_argument("--format", required=True, choices=["gltf", "obj", "mitsuba"], help="what to write")
    x.add_argument("--texture-size", type=_positive_int, default=1024, metavar="N",
                   help="texture width and height in texels")
    x.add_argument("--branch", choices=["continuous", "discrete"], default="continuous",
                   help="bake the continuous field (texture detail) or the discrete materials (flat per material)")
    x.add_argument("--envmap", help="export this lat-long HDR image as the lighting instead of the fitted one")
    x.set_defaults(func=_cmd_export)


def _add_ui(sub, shared) -> None:
    u = sub.add_parser(
        "ui", parents=[shared["threads"]], help="edit a fitted run's materials in the browser",
        description="Start a local web server with an editor page: click a material, change its basecolor, "
                    "metallic and roughness or give it a preset, relight, undo, save the edit list as a new run "
                    "beside RUN_DIR and export it. Reach it from another machine through an SSH tunnel (docs: "
                    "README); any --host but 127.0.0.1 lets other machines open the editor.")
    u.add_argument("run_dir", help="a fitted or edited run directory")
    u.add_argument("--port", type=int, default=8080, help="TCP port to listen on (0: any free port)")
    u.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1, this machine only)")
    u.add_argument("--envmaps", metavar="DIR",
                   help="folder of .exr / .hdr envmaps to relight with (default: envmaps/ beside the capture)")
    u.add_argument("--size", type=_positive_int, default=256, metavar="PX", help="long side of the rendered view in pixels")
    u.set_defaults(func=_cmd_ui)


def _add_eval(sub, shared) -> None:
    e = sub.add_parser(
        "eval", parents=[shared["threads"], _output("metrics JSON path (default: RUN_DIR/metrics.json)"),
                         shared["quiet"], shared["size"]],
        help="score a fitted run: its held-out views, or a synthetic dataset's ground truth (--gt)",
        description="Render the dataset's test views (transforms_test.json) and compare inside the ground-truth "
                    "foreground: novel-view PSNR/SSIM, basecolor PSNR/SSIM after per-channel scale alignment, "
                    "metallic/roughness PSNR, and relighting PSNR/SSIM under each held-aside envmap (albedo-scale "
                    "and image-scale variants). DATASET is a folder written by `vq-mitsuba make-scene` "
                    "(scene.json, transforms_test.json, images/, gt/, relit/, envmaps/); without --gt, the run's "
                    "held-out views (fit --holdout K) are scored. --meanshift gives the bandwidths of the "
                    "MeanShift segmentation baseline on the continuous branch's BRDF maps ('none' skips it); it "
                    "needs ground-truth material ids. --downscale / --max-size set the held-out photos' size "
                    "(default: the fit's).")
    e.add_argument("run_dir", help="a run directory written by `vq-mitsuba fit`")
    e.add_argument("--gt", metavar="DATASET", help="the ground-truth dataset folder (default: the held-out views)")
    e.add_argument("--spp", type=_positive_int, help="render samples per pixel (default: render.spp of the run's config)")
    e.add_argument("--scale", choices=["lstsq", "median"], default="lstsq",
                   help="basecolor scale alignment: lstsq (NeRFactor) or median (TensoIR)")
    e.add_argument("--meanshift", type=_bandwidths, default=(0.2, 0.3, 0.5), metavar="BW,BW,...",
                   help="MeanShift baseline bandwidths (default 0.2,0.3,0.5; 'none' skips it)")
    e.set_defaults(func=_cmd_eval)


def _add_make_scene(sub, shared) -> None:
    m = sub.add_parser(
        "make-scene", parents=[shared["threads"], _output("output folder (default: data/NAME)")],
        help="render a bundled synthetic scene with ground truth",
        description="Render a bundled scene with Mitsuba's path tracer (or Blender Cycles with --renderer cycles: "
                    "bpy in .venv-cycles, `make cycles`; same layout, plus relit views under Blender's eight "
                    "studio-light probes): training and test views in both capture formats, ground-truth maps and "
                    "relit test views. --photo-formats also writes the training views as a NeuS/IDR capture "
                    "(neus/), COLMAP captures (colmap/: binary, pinhole; colmap_opencv/: text, distorted "
                    "OPENCV lens), a nerfstudio capture (nerfstudio/: transforms.json, per-frame OPENCV lenses) "
                    "and an LLFF capture (llff/: poses_bounds.npy).")
    m.add_argument("name", nargs="?", help="scene name (see --list)")
    m.add_argument("--resolution", type=_resolution, metavar="N|WxH",
                   help="image size in pixels: N for N x N, or W x H (default per scene)")
    m.add_argument("--photo-formats", action="store_true",
                   help="also write the training views as NeuS/IDR, COLMAP, nerfstudio and LLFF captures")
    m.add_argument("--spp", type=_positive_int,
                   help="path-tracing samples per pixel (default: the scene's for mitsuba, 128 for cycles)")
    m.add_argument("--renderer", choices=["mitsuba", "cycles"], default="mitsuba",
                   help="mitsuba (default) or cycles (Blender Cycles, `make cycles`)")
    m.add_argument("--n-train", type=_positive_int, help="number of training views")
    m.add_argument("--n-test", type=_positive_int, help="number of test views")
    m.add_argument("--seed", type=int, default=0, help="random seed")
    m.add_argument("--list", action="store_true", help="list the bundled scenes")
    m.set_defaults(func=_cmd_make_scene)


def _add_batch(sub, shared) -> None:
    b = sub.add_parser(
        "batch", parents=[shared["threads"], _output("the batch's folder: one run per capture and seed", metavar="OUT",
                                                     required=True), shared["config"], shared["size"], shared["quiet"]],
        help="fit many captures (and seeds) at once as Ray tasks, here or on a cluster",
        description="Fit each CAPTURE under each seed into OUT/<capture>[-<preset>]-s<seed>/ with the ordinary "
                    "`fit` (and `eval` with --eval: against the ground truth of a make-scene dataset, else the "
                    "held-out views), each as a Ray task reserving --threads-per-run CPUs. Without --address "
                    "Ray starts on this machine's cores. Rerun the command to skip finished runs and resume the "
                    "others. Writes OUT/batch.json (each run's status), OUT/logs/, OUT/summary.csv and "
                    "OUT/summary.md; exits 1 when a run failed.")
    b.add_argument("captures", nargs="+", metavar="CAPTURE", help="captures to fit (any format `fit` reads)")
    b.add_argument("--seeds", default="0", metavar="S,S,...", help="fit each capture once per seed (default 0)")
    b.add_argument("--eval", action="store_true", help="score each run after its fit (`vq-mitsuba eval`)")
    b.add_argument("--address", metavar="ADDR", help="join this running Ray cluster (e.g. ray://HEAD:10001 or auto)")
    b.add_argument("--threads-per-run", type=_positive_int, default=1, metavar="N",
                   help="CPU threads each run reserves and uses (default 1)")
    b.set_defaults(func=_cmd_batch, resume=False)


SUBCOMMANDS = (_add_fit, _add_geometry, _add_pose, _add_render, _add_edit, _add_export, _add_ui, _add_eval,
               _add_make_scene, _add_batch)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vq-mitsuba",
        description="Neural reflectance decomposition (VQ-NeRF) on Mitsuba 3: fit materials and lighting "
                    "to posed images, then render novel views, material maps and relighting.",
    )
    sub = p.add_subparsers(dest="command", required=True)
    shared = _shared_parents()
    for add in SUBCOMMANDS:
        add(sub, shared)
    return p


MANUAL_WIDTH = 100  # columns of docs/cli.md's help texts, whatever the terminal


def manual() -> str:
    """docs/cli.md: every command's --help, as argparse prints it (`python -m vq_mitsuba.cli
    --manual > docs/cli.md`; a test holds the file to it byte for byte)."""
    import os

    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(MANUAL_WIDTH)  # argparse wraps at the terminal's width
    try:
        parser = build_parser()
        commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        lines = ["# The command line", "",
                 "Generated from the parsers by `python -m vq_mitsuba.cli --manual > docs/cli.md`; a test "
                 "checks it is current.", "", "```", parser.format_help().rstrip(), "```"]
        for name, sub in commands.choices.items():
            lines += ["", f"## `vq-mitsuba {name}`", "", "```", sub.format_help().rstrip(), "```"]
    finally:
        if before is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = before
    return "\n".join(lines) + "\n"


def _join_negative_lists(argv: list[str]) -> list[str]:
    """`--box -1,0,-1,1,1,1` as `--box=-1,0,...`: argparse would take a value starting with '-' for an option."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] == "--box" and i + 1 < len(argv) and argv[i + 1].startswith("-") and "," in argv[i + 1]:
            out.append(f"--box={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


@contextmanager
def _warnings_as_messages():
    """Warnings of the libraries (PIL, scikit-learn, OpenEXR, ...) shown as one `warning:` line each,
    once, without their source line; scikit-learn's k-means convergence notes (duplicate latents
    early in a fit, expected) are dropped."""
    seen = set()

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message).strip().splitlines()[0] if str(message).strip() else category.__name__
        if text not in seen:
            seen.add(text)
            print(f"warning: {text}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Number of distinct clusters")
        warnings.showwarning = show
        yield


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(_join_negative_lists(sys.argv[1:] if argv is None else list(argv)))
    try:
        from vq_mitsuba.backend import set_threads
        from vq_mitsuba.run.loop import interrupt_signals

        # SIGTERM ends a command as Ctrl-C does: a fit writes its checkpoint and releases the run's lock
        with _warnings_as_messages(), interrupt_signals():
            set_threads(args.threads)
            return args.func(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:  # a write the machine refused outside RunDir's writers (images of render, make-scene)
        from vq_mitsuba.run.write_errors import as_write_error

        error = as_write_error(exc)
        if error is None:
            raise
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt as exc:
        resumable = args.command in ("fit", "geometry")
        print("interrupted" + (f"; the last checkpoint is kept (continue with `vq-mitsuba {args.command} ... --resume`)"
                               if resumable else ""), file=sys.stderr)
        return 128 + getattr(exc, "signum", 2)  # 130 for SIGINT, 143 for SIGTERM


if __name__ == "__main__":
    if sys.argv[1:] == ["--manual"]:
        print(manual(), end="")
        sys.exit(0)
    sys.exit(main())
