"""`vq-mitsuba geometry`: the geometry method (NeuS) and mesh export into a run
(`vq_mitsuba.engine.pipeline.geometry_capture`)."""

from __future__ import annotations

from vq_mitsuba.cli.common import command_config, help_config, refuse_file_output, run_dir_of, run_parents


def add_parser(sub, shared) -> None:
    g = sub.add_parser(
        "geometry", parents=run_parents(shared), help="reconstruct a mesh from posed images, with or without masks (NeuS)",
        description="NeuS on the capture's images (and masks, when it has any), then marching cubes and mesh "
                    "clean-up; photos or a video are posed first (RUN_DIR/pose/). Writes RUN_DIR/mesh.ply, "
                    "geometry.json (timings, settings), geometry_loss.png and the NeuS checkpoint neus.pt. Known "
                    "geometry in the capture is ignored. Of the config, the `neus`, `capture` and `pose` sections "
                    "apply (e.g. --set neus.iterations=3000).")
    g.add_argument("--gt-mesh", help="score the mesh against this ground-truth mesh (Chamfer, normal consistency)")
    g.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.engine.pipeline import geometry_capture
    from vq_mitsuba.geometry import methods
    from vq_mitsuba.geometry.stage import check_geometry_target
    from vq_mitsuba.run.run_dir import RunDir

    if args.help_config:
        return help_config()
    run_dir = run_dir_of(args, "geometry")
    refuse_file_output(run_dir)
    check_geometry_target(RunDir(run_dir))
    cfg = command_config(args)
    result = geometry_capture(args.capture, run_dir, cfg, resume=args.resume, gt_mesh=args.gt_mesh)
    info = result.summary
    lines = methods.get(result.method).report(info)  # its training first, then its own scores
    mesh = f"mesh with {len(result.mesh.faces)} faces in {run_dir}/{RunDir.MESH}"
    print("; ".join([*lines[:1], mesh]))
    for line in lines[1:]:
        print(line)
    if "metrics" in info:
        m = info["metrics"]
        print(f"against {args.gt_mesh}: Chamfer {100 * m['chamfer_rel']:.3f}% of the bounding-box diagonal, "
              f"normal consistency {m['normal_consistency']:.4f}, shading normals off by "
              f"{m['shading_normal_deg_median']:.2f} degrees (median)")
    return 0
