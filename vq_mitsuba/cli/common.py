"""What several commands share: the option types, the shared options (each defined once, as
argparse parents), the config a command runs with, and the output-folder checks."""

from __future__ import annotations

import argparse
from pathlib import Path

from vq_mitsuba.errors import InputError

RUN_DIR_OUTPUT = "run directory (default: runs/<capture folder name>)"


# --- option types ------------------------------------------------------------------------------
def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def nonempty_path(text: str) -> str:
    """A path on the command line; an empty one is refused (as a path it would be the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("the value is empty (give a path)")
    return text


def finite(limit: float):
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


# --- help ---------------------------------------------------------------------------------------
CAPTURE_FORMATS = "{capture formats}"  # in a description: the capture formats, each as its module describes it


class CaptureFormatsHelp(argparse.HelpFormatter):
    """Help whose description lists the capture formats (vq_mitsuba.data.formats' DESCRIPTIONs) in place
    of CAPTURE_FORMATS; the formats are imported when the help is shown, not at every start."""

    def add_text(self, text):
        if text and CAPTURE_FORMATS in text:
            from vq_mitsuba.data.formats import described

            text = text.replace(CAPTURE_FORMATS, described())
        super().add_text(text)

    def _fill_text(self, text, width, indent):  # argparse's, without breaking a name at its hyphen (NeRF-synthetic)
        import textwrap

        text = self._whitespace_matcher.sub(" ", text).strip()
        return textwrap.fill(text, width, initial_indent=indent, subsequent_indent=indent, break_on_hyphens=False)


# --- shared options ----------------------------------------------------------------------------
def _parent() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(add_help=False)


def output_option(help: str, metavar: str | None = None, required: bool = False) -> argparse.ArgumentParser:
    """-o, the one output option; `help` says what it names for the command and its default."""
    p = _parent()
    p.add_argument("-o", "--output", required=required, metavar=metavar, help=help)
    return p


def shared_parents() -> dict[str, argparse.ArgumentParser]:
    """The options several commands share, each defined once (argparse parents)."""
    threads = _parent()
    threads.add_argument("--threads", type=positive_int, metavar="N",
                         help="CPU threads for torch and Dr.Jit (default: every core this process may use)")
    device = _parent()  # the one device of the process (vq_mitsuba.backend.choose_device)
    device.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                        help="where every stage runs: auto (a GPU when Mitsuba and torch both have CUDA), cpu or cuda")
    quiet = _parent()
    quiet.add_argument("--quiet", action="store_true", help="no progress bars or notes (warnings and errors remain)")
    config = _parent()  # the config file system: docs/configuration.md
    config.add_argument("--preset", metavar="NAME", help="apply the named bundled preset (see --help-config)")
    config.add_argument("--config", metavar="FILE", help="apply a YAML config file, after --preset")
    config.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one config key, e.g. train.iterations=500 (repeatable)")
    config.add_argument("--help-config", action="store_true", help="list every config key and preset")
    size = _parent()  # how large the photos are read (config section capture): fit, geometry, render, eval
    size.add_argument("--downscale", type=positive_int, metavar="N",
                      help="divide the photos' width and height by N (capture.downscale)")
    size.add_argument("--max-size", type=int, metavar="N",
                      help="shrink each photo as it is read to at most N pixels a side (capture.max_size)")
    # the capture, and how its images are read (config section capture)
    capture = argparse.ArgumentParser(add_help=False, parents=[size])
    capture.add_argument("capture", nargs="?", help="the capture: a file or folder of a format docs/captures.md "
                                                    "lists, a folder of photos or a video")
    capture.add_argument("--background-color", metavar="R,G,B",
                         help="key out a plain backdrop of this sRGB colour (0..1) as the mask")
    capture.add_argument("--holdout", type=positive_int, metavar="K",
                         help="keep every K-th view out of training, for `eval RUN_DIR` (capture.holdout)")
    resume = _parent()
    resume.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    return {"threads": threads, "device": device, "quiet": quiet, "config": config, "size": size, "capture": capture,
            "resume": resume}


def run_parents(shared) -> list:
    """The options of the commands that write a run folder from a capture (fit, geometry)."""
    return [shared["threads"], shared["device"], output_option(RUN_DIR_OUTPUT)] + [
        shared[k] for k in ("capture", "config", "resume", "quiet")]


# --- the config a command runs with ------------------------------------------------------------
def help_config() -> int:
    from vq_mitsuba.config import describe, presets

    print("Config keys (set them in a preset, a YAML file, or with --set section.key=value):")
    print("\n".join(describe()))
    print(f"Presets (--preset NAME): {', '.join(presets())}")
    return 0


def command_config(args, run_dir: Path | None = None):
    """Defaults <- the run's saved config (on --resume) <- --preset <- --config <- --set."""
    from vq_mitsuba.config import load_config
    from vq_mitsuba.run.run_dir import RunDir

    base = RunDir(run_dir).saved_config() if (args.resume and run_dir is not None) else None
    return load_config(args.config, capture_flags(args) + list(args.set), base=base, preset=args.preset)


def capture_flags(args) -> list[str]:
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


# --- output folders ----------------------------------------------------------------------------
def run_dir_of(args, command: str) -> Path:
    """RUN_DIR of a command that reads a CAPTURE: -o, else runs/<name of the capture's folder> (of
    the folder itself when CAPTURE is one, e.g. of photos; a video's name)."""
    from vq_mitsuba.data.unposed import capture_name

    if args.capture is None:
        raise InputError(None, f"{command} needs a CAPTURE (scene XML, transforms json, or its folder)")
    return Path(args.output) if args.output else Path("runs") / capture_name(args.capture)


def refuse_file_output(path: str | Path | None) -> None:
    """-o names a folder: refuse an existing file before any work."""
    if path is not None and Path(path).exists() and not Path(path).is_dir():
        raise InputError(path, "is a file; -o names an output folder")
