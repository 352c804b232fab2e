"""`vq-mitsuba edit`: a new run with changed materials (`vq_mitsuba.edit.build_edit`, `edit_run`)."""

from __future__ import annotations

from vq_mitsuba import brdf
from vq_mitsuba.cli.common import finite, output_option, refuse_file_output
from vq_mitsuba.errors import InputError


def _either(words: list[str]) -> str:
    """"a, b or c"."""
    return ", ".join(words[:-1]) + " or " + words[-1] if len(words) > 1 else "".join(words)


def _set_forms() -> str:
    """What --set takes, input by input, e.g. "basecolor=R,G,B (linear, 0..1) or basecolor=#RRGGBB (sRGB), ..."."""
    return _either([f"{i.name}=R,G,B (linear, 0..1) or {i.name}=#RRGGBB (sRGB)" if i.colour else f"{i.name}=V"
                    for i in brdf.INPUTS])


def add_parser(sub, shared) -> None:
    d = sub.add_parser(
        "edit", parents=[shared["threads"], output_option("the edited run to write", metavar="NEW_RUN")],
        help="select materials of a fitted run and change them (writes a new run)",
        description="Select surface points by ranked material, by the material under a pixel, and / or by a "
                    "world-space box (material and box selections intersect), and change their BRDF. Writes "
                    "NEW_RUN with run.json naming RUN_DIR's fitted run and edits.json, the edit list (RUN_DIR's "
                    "edits plus this one); render, export and eval of NEW_RUN show the edit. --set takes "
                    f"{_set_forms()}; --scale multiplies {_either(list(brdf.NAMES))} by F, keeping the texture "
                    "(clamped to 0..1).")
    d.add_argument("run_dir", nargs="?", help="a fitted (or already edited) run directory")
    d.add_argument("--material", type=int, action="append", default=[], metavar="K",
                   help="select the K-th ranked material (materials.json; repeatable)")
    d.add_argument("--pick", action="append", default=[], metavar="VIEW:X,Y",
                   help="select the material under pixel X,Y of the capture's (or its test cameras') view VIEW")
    d.add_argument("--box", action="append", default=[], metavar="x0,y0,z0,x1,y1,z1",
                   help="keep only points inside this world-space box (the capture's coordinates; repeatable)")
    d.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help=f"set {_either(list(brdf.NAMES))} of the selection (see above)")
    d.add_argument("--scale", action="append", default=[], metavar="KEY=F",
                   help=f"multiply {_either(list(brdf.NAMES))} by F (see above)")
    d.add_argument("--hue-shift", type=finite(1e6), metavar="DEG", help="rotate the basecolor's hue by DEG degrees")
    d.add_argument("--preset", metavar="NAME", help="a named material of the library (see --list-presets)")
    d.add_argument("--list-presets", action="store_true", help="list the library's materials")
    d.set_defaults(func=run)


def edit_label(args) -> str:
    """The edit as the user asked for it, e.g. "--material 2 --preset gold" (stored with the edit)."""
    parts = [f"--material {k}" for k in args.material] + [f"--pick {p}" for p in args.pick]
    parts += [f"--box {b}" for b in args.box] + ([f"--preset {args.preset}"] if args.preset else [])
    parts += [f"--set {x}" for x in args.set] + [f"--scale {x}" for x in args.scale]
    return " ".join(parts + ([f"--hue-shift {args.hue_shift:g}"] if args.hue_shift is not None else []))


def run(args) -> int:
    from vq_mitsuba.edit import build_edit, edit_run
    from vq_mitsuba.run.outputs import check_output_folder
    from vq_mitsuba.run.run_dir import RunDir, check_writable
    from vq_mitsuba.models.material_edits import material_library

    if args.list_presets:
        for name, m in sorted(material_library().items()):
            values = " ".join(f"{i.name} {m[i.name]}" for i in brdf.INPUTS)
            print(f"{name:14s} {values}  ({m['note']})")
        return 0
    if args.output is None:
        raise InputError(None, "edit writes a new run: give it a folder with -o NEW_RUN")
    refuse_file_output(args.output)
    check_output_folder(args.output, "edit", "edit")
    check_writable(args.output)
    run = RunDir(args.run_dir)
    fitted = run.load()
    edit = build_edit(run, fitted, args.material, args.pick, args.box, args.set, args.scale, args.hue_shift,
                      args.preset, label=edit_label(args))
    out = edit_run(run, args.output, edit)
    sel = edit.selection
    what = (f"material{'s' if len(sel.materials) > 1 else ''} {', '.join(map(str, sel.materials))}"
            if sel.materials else "every material") + \
        (f" inside {len(sel.boxes)} box(es)" if sel.boxes else "")
    print(f"edited {what}: {len(edit.changes)} change(s); {len(out.edits())} edit(s) in {out.dir / RunDir.EDITS}")
    print(f"render it with: vq-mitsuba render {out.dir} --cameras CAMERAS")
    return 0
