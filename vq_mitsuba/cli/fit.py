"""`vq-mitsuba fit`: the whole fit is `vq_mitsuba.engine.pipeline.fit_capture`."""

from __future__ import annotations

from vq_mitsuba.cli.common import (CAPTURE_FORMATS, CaptureFormatsHelp, command_config, help_config, refuse_file_output,
                                   run_dir_of, run_parents)


def add_parser(sub, shared) -> None:
    from vq_mitsuba.geometry import methods

    modes = methods.fit_modes()
    f = sub.add_parser(
        "fit", parents=run_parents(shared), help="decompose a capture into materials and lighting (VQ-NeRF)",
        formatter_class=CaptureFormatsHelp,
        description="Fit VQ-NeRF to a capture: geometry (given, or NeuS from the images), the continuous and "
                    "discrete material branches, the lighting if unknown, and the ranked materials. The capture "
                    f"is {CAPTURE_FORMATS} (docs/captures.md); photos and a video are posed first, by structure "
                    "from motion. Writes RUN_DIR (docs/run_dir.md): run.json, config.yaml, checkpoint.pt, mesh.ply, envmap.exr, materials.json, "
                    "materials_err.png, materials_sheet.png, loss.png, fit.json, residual.pt. --geometry auto (the "
                    "default) uses the capture's shapes, its mesh.ply or --mesh when there are any, and otherwise "
                    "reconstructs the mesh with NeuS first (RUN_DIR/mesh.ply, reused on --resume); neus always "
                    "reconstructs it from the images (with their masks when they have any); given never does.")
    f.add_argument("--mesh", help="known geometry (PLY/OBJ) in the capture's world, for any posed capture")
    f.add_argument("--geometry", choices=list(modes), default="auto",
                   help=f"where the mesh comes from: {modes[0]} (default), {', '.join(modes[1:-1])} or {modes[-1]} "
                        "(see above)")
    f.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.engine.pipeline import fit_capture
    from vq_mitsuba.run.run_dir import RunDir, check_writable

    if args.help_config:
        return help_config()
    run_dir = run_dir_of(args, "fit")
    refuse_file_output(run_dir)
    check_writable(run_dir)
    cfg = command_config(args, run_dir)  # bad keys and values fail before any work
    summary = fit_capture(args.capture, run_dir, cfg, geometry=args.geometry, mesh=args.mesh, resume=args.resume)
    print(f"fitted {summary['iterations']} iterations in {summary['seconds']:.1f} s "
          f"({summary['iterations_per_s']:.1f} it/s); results in {run_dir}/")
    materials = RunDir(run_dir).materials()
    if materials is not None and cfg.vq.enabled:
        print(f"materials: M = {materials['num_materials']} ({run_dir}/materials.json, materials_sheet.png, "
              "materials_err.png)")
    return 0
