"""`vq-mitsuba make-scene`: a bundled synthetic dataset (`vq_mitsuba.synthetic.mitsuba_scenes.make_scene`,
or `cycles.make_scene_cycles`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vq_mitsuba.cli.common import output_option, positive_int
from vq_mitsuba.errors import InputError, as_write_error


def resolution(text: str):
    """N (an int) or WxH (a tuple)."""
    parts = text.lower().split("x")
    if len(parts) == 1:
        return positive_int(parts[0])
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"'{text}' is neither N nor WxH")
    return positive_int(parts[0]), positive_int(parts[1])


def add_parser(sub, shared) -> None:
    m = sub.add_parser(
        "make-scene", parents=[shared["threads"], output_option("output folder (default: data/NAME)")],
        help="render a bundled synthetic scene with ground truth",
        description="Render a bundled scene with Mitsuba's path tracer (or Blender Cycles with --renderer cycles: "
                    "bpy in .venv-cycles, `make cycles`; same layout, plus relit views under Blender's eight "
                    "studio-light probes): training and test views in both capture formats, ground-truth maps and "
                    "relit test views. --photo-formats adds neus/, colmap/ (binary, pinhole), colmap_opencv/ "
                    "(text, distorted OPENCV lens), nerfstudio/ (per-frame OPENCV lenses) and llff/.")
    m.add_argument("name", nargs="?", help="scene name (see --list)")
    m.add_argument("--resolution", type=resolution, metavar="N|WxH",
                   help="image size in pixels: N for N x N, or W x H (default per scene)")
    m.add_argument("--photo-formats", action="store_true",
                   help="also write the training views as NeuS/IDR, COLMAP, nerfstudio and LLFF captures")
    m.add_argument("--spp", type=positive_int,
                   help="path-tracing samples per pixel (default: the scene's for mitsuba, 128 for cycles)")
    m.add_argument("--renderer", choices=["mitsuba", "cycles"], default="mitsuba",
                   help="mitsuba (default) or cycles (Blender Cycles, `make cycles`)")
    m.add_argument("--n-train", type=positive_int, help="number of training views")
    m.add_argument("--n-test", type=positive_int, help="number of test views")
    m.add_argument("--seed", type=int, default=0, help="random seed")
    m.add_argument("--list", action="store_true", help="list the bundled scenes")
    m.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.data.dataset_dir import DatasetDir
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
        try:
            cycles.make_scene_cycles(args.name, out, seed=args.seed, **kwargs)
        except OSError as exc:  # a refused write that names no file (the writers name theirs): the folder
            error = as_write_error(exc, exc.filename or out)
            if error is None:
                raise
            raise error from None
    else:
        synthetic.make_scene(args.name, out, seed=args.seed, photo_formats=args.photo_formats, **kwargs)
    files = (DatasetDir.SCENE_XML, DatasetDir.TRANSFORMS_TRAIN, DatasetDir.TRANSFORMS_TEST, DatasetDir.GT + "/",
             DatasetDir.RELIT + "/")
    print(f"scene '{args.name}' rendered with {args.renderer} to {out}/ ({', '.join(files)})")
    return 0
