"""`vq-mitsuba export`: baked textures and a glTF, OBJ or Mitsuba scene (`vq_mitsuba.export.formats.export_run`)."""

from __future__ import annotations

from vq_mitsuba.cli.common import output_option, refuse_file_output


def add_parser(sub, shared) -> None:
    x = sub.add_parser(
        "export", parents=[shared["threads"], shared["device"], output_option("output folder", metavar="OUT", required=True),
                           shared["quiet"]],
        help="take a fitted or edited run to Blender, three.js or Mitsuba",
        description="UV-unwrap the mesh, bake basecolor, metallic, roughness and the material ids into textures, "
                    "and write a glTF binary (.glb, metallic-roughness PBR), OBJ+MTL (PBR keys) or a Mitsuba scene "
                    "XML (mesh, principled with textures, envmap, the capture's cameras). The lighting goes beside "
                    "it as envmap.exr and envmap.hdr.")
    x.add_argument("run_dir", help="a fitted or edited run directory")
    x.add_argument("--format", required=True, choices=["gltf", "obj", "mitsuba"], help="what to write")
    x.add_argument("--texture-size", default=1024, metavar="N",
                   help="texture width and height in texels")
    x.add_argument("--branch", choices=["continuous", "discrete"], default="continuous",
                   help="bake the continuous field (texture detail) or the discrete materials (flat per material)")
    x.add_argument("--envmap", help="export this lat-long HDR image as the lighting instead of the fitted one")
    x.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.export.formats import check_texture_size, export_run

    try:
        size = int(args.texture_size)
    except ValueError:
        size = args.texture_size  # refused below, as given
    size = check_texture_size(size, "--texture-size")  # export's one bound and message, naming the option
    refuse_file_output(args.output)
    summary = export_run(args.run_dir, args.format, args.output, size, args.branch, args.envmap)
    s = summary["seconds"]
    print(f"exported {summary['format']} ({summary['branch']} branch, {summary['texture_size']}^2 textures, "
          f"baked in {s['bake']:.1f} s) to {args.output}/: {', '.join(summary['files'])}")
    return 0
