"""Command line: `vq-mitsuba fit | geometry | pose | render | edit | export | ui | eval | make-scene | batch`.

One module per command, each with its parser (`add_parser`) and its handler (`run`: the checks of
its arguments, one library call and its report); the options several commands share are defined
once in `common`. The handlers import their libraries when they run, so `render` loads no training
code."""

from __future__ import annotations

import argparse
import re
import sys
import warnings
from contextlib import contextmanager

from vq_mitsuba.cli import batch, edit, export, fit, geometry, make_scene, pose, render, ui
from vq_mitsuba.cli import eval as evaluate
from vq_mitsuba.cli.common import command_config as _config, run_dir_of as _run_dir, shared_parents
from vq_mitsuba.errors import UserError

__all__ = ["main", "build_parser", "manual", "COMMANDS", "_config", "_run_dir"]  # _config, _run_dir: older names

COMMANDS = (fit, geometry, pose, render, edit, export, ui, evaluate, make_scene, batch)
MANUAL_WIDTH = 100  # columns of docs/cli.md's help texts, whatever the terminal


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("vq-mitsuba")
    except PackageNotFoundError:  # run from a checkout that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vq-mitsuba",
        description="Neural reflectance decomposition (VQ-NeRF) on Mitsuba 3: fit materials and lighting "
                    "to posed images, then render novel views, material maps and relighting.",
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    shared = shared_parents()
    for command in COMMANDS:
        command.add_parser(sub, shared)
    return p


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
    """`--box -1,0,-1,1,1,1` as `--box=-1,0,...` (and so for every option given a list of numbers that
    starts negative): argparse would take a value starting with '-' for an option."""
    out, i = [], 0
    while i < len(argv):
        value = argv[i + 1] if i + 1 < len(argv) else ""
        if argv[i].startswith("--") and "=" not in argv[i] and re.match(r"^-[\d.]", value) and "," in value:
            out.append(f"{argv[i]}={value}")
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


def _kept(args) -> str:
    """What a command stopped by a signal kept, and how to go on from there."""
    if args.command == "batch":
        return "; finished runs and checkpoints are kept (run the same command again to resume)"
    if args.command == "pose":
        return "; nothing half-written is kept (run the same command again)"
    if args.command not in ("fit", "geometry"):
        return ""
    try:
        folder = _run_dir(args, args.command)
    except UserError:
        folder = None
    if folder is not None and not folder.is_dir():  # stopped before anything was written (e.g. while posing)
        return "; nothing was kept yet (run the same command again, without --resume)"
    return f"; the last checkpoint is kept (continue with `vq-mitsuba {args.command} ... --resume`)"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(_join_negative_lists(sys.argv[1:] if argv is None else list(argv)))
    try:
        from vq_mitsuba.backend import choose_device, set_threads
        from vq_mitsuba.messages import quiet
        from vq_mitsuba.run.loop import interrupt_signals

        # SIGTERM ends a command as Ctrl-C does: a fit writes its checkpoint and releases the run's lock;
        # a signal whose exception a library lost ends the command as stopped once its work returns.
        # --quiet silences every note and progress bar here, in one place (warnings and errors remain).
        with _warnings_as_messages(), interrupt_signals(), quiet(getattr(args, "quiet", False)):
            set_threads(args.threads)
            if getattr(args, "device", None):  # the commands that compute: one device for the process
                choose_device(args.device)
            return args.func(args)
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:  # a write the machine refused outside RunDir's writers (images of render, make-scene)
        from vq_mitsuba.errors import as_write_error

        error = as_write_error(exc)
        if error is None:
            raise
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt as exc:
        print("interrupted" + _kept(args), file=sys.stderr)
        from vq_mitsuba.run.loop import stop_status

        return stop_status(exc)  # 130 for SIGINT, 143 for SIGTERM
