"""Where a command may write: one rule for every command that writes.

A command writes only into a new folder, an empty one, or a folder of its own kind that it made
before, known by that kind's marker file:

    run       (fit, geometry)  run.json or another file only a run holds (RunDir.markers())
    render                     render.json
    export                     export.json naming the same format
    pose                       pose.json, readable and made from the same photos (geometry/poses.py)
    scene     (make-scene)     a readable scene.json (or the mark of an interrupted make-scene) and
                               nothing a dataset does not hold: replaced whole
    batch                      batch.json
    edit                       none: an edit writes a new run

Anything else is refused before any work with an InputError naming the folder, what it holds
and what to do: no command writes over a file that another command or the user made. A file
output (`eval -o`) replaces only a metrics file that eval wrote. A command refused after it began
(a refusal that needs the capture read) removes what it made (`removed_on_refusal`).
"""

from __future__ import annotations

import json
import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from vq_mitsuba.data.dataset_dir import DatasetDir
from vq_mitsuba.errors import InputError
from vq_mitsuba.run.run_dir import RunDir

RENDER_MARKER = "render.json"
EXPORT_MARKER = "export.json"
POSE_MARKER = "pose.json"
SCENE_MARKER = DatasetDir.INFO
BATCH_MARKER = "batch.json"
SCENE_INCOMPLETE = DatasetDir.INCOMPLETE  # in a dataset folder while make-scene writes it
EVAL_MARK = {"written_by": "vq-mitsuba eval"}  # a key of every metrics file eval writes

# Entries a run keeps besides its files, which alone do not make a folder another's.
_RUN_CACHES = (RunDir.LOCK, RunDir.UNDISTORTED)
_OWN = {"run": "vq-mitsuba run", "render": "render (render.json)", "export": "export (export.json)",
        "scene": "make-scene dataset (scene.json)", "batch": "batch (batch.json)"}


def _entries(folder: Path) -> list[Path]:
    try:
        return sorted(folder.iterdir())
    except OSError as exc:
        raise InputError(folder, f"cannot be read ({exc.strerror or exc}): choose another -o") from None


def _json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def describe(folder: str | Path) -> str:
    """What `folder` holds, in words, e.g. "a render (render.json)" or "other files (a.png, b.txt)"."""
    folder = Path(folder)
    run = RunDir(folder)
    if (folder / RunDir.INFO).is_file():
        info = _json(folder / RunDir.INFO) or {}
        if "edit_of" in info:
            return "an edited run (run.json, edits.json)"
        if run.has_checkpoint():
            return "a fitted run (run.json, checkpoint.pt)"
        return "a vq-mitsuba run (run.json)"
    if run.holds_run_files():
        found = [m for m in RunDir.markers() if (folder / m).is_file()]
        return f"an unfinished vq-mitsuba run ({', '.join(found)})"
    if (folder / RENDER_MARKER).is_file():
        return "a render (render.json)"
    if (folder / EXPORT_MARKER).is_file():
        fmt = (_json(folder / EXPORT_MARKER) or {}).get("format")
        return f"{'a ' + str(fmt) if isinstance(fmt, str) else 'an'} export (export.json)"
    if (folder / POSE_MARKER).is_file():
        return "a posed capture (pose.json)"
    if (folder / SCENE_MARKER).is_file() or (folder / SCENE_INCOMPLETE).is_file():
        return "a make-scene dataset (scene.json)"
    if (folder / BATCH_MARKER).is_file():
        return "a batch (batch.json)"
    names = [p.name + ("/" if p.is_dir() else "") for p in _entries(folder)]
    shown = ", ".join(names[:3]) + (f", ... {len(names)} in all" if len(names) > 3 else "")
    return f"other files ({shown})"


def is_empty(folder: Path, ignore: tuple[str, ...] = ()) -> bool:
    return not any(p.name not in ignore for p in _entries(folder))


def is_own(folder: Path, kind: str, fmt: str | None = None) -> bool:
    """Whether `folder` is a folder of `kind` that its command made before (see the module's table)."""
    if kind == "run":
        run = RunDir(folder)
        return run.holds_run_files() or is_empty(folder, _RUN_CACHES)
    if kind == "render":
        return (folder / RENDER_MARKER).is_file() and not RunDir(folder).holds_run_files()
    if kind == "export":
        summary = _json(folder / EXPORT_MARKER)
        return summary is not None and summary.get("format") == fmt and not RunDir(folder).holds_run_files()
    if kind == "scene":
        return ((folder / SCENE_MARKER).is_file() or (folder / SCENE_INCOMPLETE).is_file()) \
            and not RunDir(folder).holds_run_files()
    if kind == "batch":
        return (folder / BATCH_MARKER).is_file() and not RunDir(folder).holds_run_files()
    if kind == "edit":
        return False
    raise ValueError(f"unknown output kind {kind!r}")


def check_output_folder(folder: str | Path, kind: str, command: str, fmt: str | None = None) -> None:
    """Refuse, before any work, an output folder that is not new, empty, or `kind`'s own (for an
    export, of the format `fmt`): an InputError naming it, what it holds and what to do."""
    folder = Path(folder)
    if not folder.exists():
        return
    if not folder.is_dir():
        raise InputError(folder, "is a file; -o names an output folder")
    if is_empty(folder, (RunDir.LOCK,)):
        return
    if is_own(folder, kind, fmt):
        if kind == "scene":  # replaced whole: only when provably make-scene's, with nothing else beside
            DatasetDir(folder).check_replaceable(command)
        return
    what = describe(folder)
    if kind == "export" and (folder / EXPORT_MARKER).is_file() and not RunDir(folder).holds_run_files():
        raise InputError(folder, f"holds {what}: a {fmt} export would mix its files with it; choose another -o "
                                 "(e.g. a new folder per format)")
    if kind == "edit":
        raise InputError(folder, f"holds {what}: an edit writes a new run into a new or empty folder; "
                                 "choose another -o")
    own = _OWN[kind]
    raise InputError(folder, f"holds {what} and no {own}: {command} writes only into a new or empty folder or "
                             f"{'an' if own[0] in 'aeiou' else 'a'} {own} it made before; choose another -o")


def is_metrics_file(path: Path) -> bool:
    """Whether `path` is a metrics file `vq-mitsuba eval` wrote (also one written before eval marked
    its files: the run it scored and its novel-view scores)."""
    data = _json(path)
    if data is None:
        return False
    return all(data.get(k) == v for k, v in EVAL_MARK.items()) or ("run" in data and "novel_view" in data)


def check_metrics_file(path: str | Path) -> None:
    """Refuse, before any work, an `eval -o` that would replace a file eval did not write, or that
    takes the name of a run's own file inside a run folder."""
    folder_named = str(path).endswith(("/", "\\"))
    path = Path(path)
    if path.is_dir() or folder_named:
        raise InputError(path, "is a folder; eval -o names the metrics JSON file (e.g. -o OUT/metrics.json)")
    run_files = {Path(v).name for k, v in vars(RunDir).items() if k.isupper() and isinstance(v, str)}
    run_files |= set(RunDir.method_files())
    if path.name in run_files - {RunDir.METRICS} and RunDir(path.parent).holds_run_files():
        raise InputError(path, f"is a file of the run {path.parent}: eval -o names a metrics file of its own "
                               f"(e.g. -o {path.parent / RunDir.METRICS} or a file outside the run)")
    if path.exists() and not is_metrics_file(path):
        raise InputError(path, "exists and is not a metrics file of vq-mitsuba eval: eval replaces only its "
                               "own; name a new file with -o")


@contextmanager
def removed_on_refusal(folder: str | Path):
    """Run the body; if it is refused (an InputError), remove the entries it added to `folder` (those
    that were not there before), so that a refused command leaves nothing behind (a folder left
    empty goes with the run's lock)."""
    folder = Path(folder)
    before = {p.name for p in folder.iterdir()} if folder.is_dir() else None
    try:
        yield folder
    except InputError:
        if folder.is_dir():
            for entry in folder.iterdir():
                if (before is None or entry.name not in before) and entry.name != RunDir.LOCK:
                    if entry.is_dir() and not entry.is_symlink():
                        shutil.rmtree(entry, ignore_errors=True)
                    else:
                        entry.unlink(missing_ok=True)
        raise
