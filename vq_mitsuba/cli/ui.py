"""`vq-mitsuba ui`: the browser editor of a run (`vq_mitsuba.ui.server.serve`)."""

from __future__ import annotations

from pathlib import Path

from vq_mitsuba.cli.common import positive_int
from vq_mitsuba.errors import InputError


def add_parser(sub, shared) -> None:
    u = sub.add_parser(
        "ui", parents=[shared["threads"], shared["device"]], help="edit a fitted run's materials in the browser",
        description="Start a local web server with an editor page: click a material, change its basecolor, "
                    "metallic and roughness or give it a preset, relight, undo, save the edit list as a new run "
                    "beside RUN_DIR and export it. Reach it from another machine through an SSH tunnel (docs: "
                    "README); any --host but 127.0.0.1 lets other machines open the editor.")
    u.add_argument("run_dir", help="a fitted or edited run directory")
    u.add_argument("--port", type=int, default=8080, help="TCP port to listen on (0: any free port)")
    u.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1, this machine only)")
    u.add_argument("--envmaps", metavar="DIR",
                   help="folder of .exr / .hdr envmaps to relight with (default: envmaps/ beside the capture)")
    u.add_argument("--size", type=positive_int, default=256, metavar="PX", help="long side of the rendered view in pixels")
    u.set_defaults(func=run)


def run(args) -> int:
    from vq_mitsuba.ui.server import serve

    if not 0 <= args.port <= 65535:
        raise InputError(None, f"--port {args.port}: a port is 0..65535 (0: any free port)")
    if args.envmaps is not None and not Path(args.envmaps).is_dir():
        raise InputError(Path(args.envmaps), "is not a folder (--envmaps names a folder of .exr / .hdr files)")
    serve(args.run_dir, host=args.host, port=args.port, envmap_dir=args.envmaps, size=args.size)
    return 0
