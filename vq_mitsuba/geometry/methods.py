"""Geometry methods by name: how a mesh is reconstructed from a posed capture (NeuS is the first).

A method registers itself under its name (`register`, as instant-nsr-pl's `models.register` and
Mitsuba's plugins do); `fit --geometry NAME` picks it, `auto` and `vq-mitsuba geometry` take
`DEFAULT`. It reconstructs into a run (`GeometryMethod.reconstruct`) and returns a `Reconstruction`:
the mesh in the capture's world and its own record. The stage around it (`vq_mitsuba.geometry.stage`)
checks the folder, scores the mesh against a ground truth when asked, and writes geometry.json, then
mesh.ply. What is a method's own (its config section, checkpoint, scores and the lines that tell people
about them) stays in its package; the rest of the code asks this registry or the `Reconstruction`.

The built-in methods register when the registry is first asked (`BUILT_IN`): each lives in a module
that imports its training code only when it reconstructs, so that naming the methods (the CLI's
choices, a run's marker files) costs no import of it."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Protocol, TypeVar

from vq_mitsuba.run.run_dir import RunDir

if TYPE_CHECKING:
    from vq_mitsuba.config import Config
    from vq_mitsuba.data.captures import CaptureSource

DEFAULT = "neus"  # what `fit --geometry auto` and `vq-mitsuba geometry` reconstruct with
MODES = ("auto", "given")  # fit --geometry's modes besides the methods' names: no method may take them
BUILT_IN = ("vq_mitsuba.geometry.neus.method",)  # modules whose import registers a method


@dataclass
class Framing:
    """Where a method reconstructed: a cube of half size `half` (world units) around `center`, in the
    capture's world, and what framed it (e.g. "visual hull", "cameras")."""

    center: tuple[float, float, float]
    half: float
    source: str | None = None


@dataclass
class Reconstruction:
    """What a geometry method made of a capture (`GeometryMethod.reconstruct`). The stage writes
    `summary` as the run's geometry.json (adding the ground-truth scores and `background`, from
    `masks_from_mesh`) and `mesh` as mesh.ply."""

    mesh: object  # trimesh.Trimesh, in the capture's world
    summary: dict  # the method's record for geometry.json: its settings, timings, scores
    masks_from_mesh: bool = False  # made without masks: the fit masks the views by the mesh's coverage
    framing: Framing | None = None  # where it reconstructed
    scores: dict | None = None  # its own scores (also in `summary`), e.g. NeuS's renders of the views
    files: tuple[Path, ...] = ()  # what it wrote into the run besides geometry.json and mesh.ply
    resumed: bool = False  # it continued from its own checkpoint in the run
    model: object = None  # what it trained (NeuS: the `NeuS` model), for callers that render it
    method: str = ""  # the registered name of the method that made it (set by the stage)


class GeometryMethod(Protocol):
    """A way to reconstruct a mesh from a posed capture, registered under `name`."""

    name: str  # fit --geometry NAME
    label: str  # how messages name it, e.g. "NeuS"
    files: tuple[str, ...]  # file names it keeps in a run (its checkpoint): markers of a run, what resume continues
    seed_key: str | None  # the config key of its seed (a batch sets it for each run), None without one

    def reconstruct(self, source: CaptureSource, run: RunDir, cfg: Config, resume: bool = False) -> Reconstruction:
        """Reconstruct `source` (a posed capture) into `run` with its section of `cfg`; `resume`
        continues from its own checkpoint there, if any."""

    def report(self, summary: dict) -> list[str]:
        """Lines for people about its record (a geometry.json it wrote); [] for one it did not."""


_METHODS: dict[str, GeometryMethod] = {}
_loaded = False
M = TypeVar("M")


def register(name: str) -> Callable[[type[M]], type[M]]:
    """Class decorator: register an instance of the class as the geometry method `name`; its files
    become markers of a run (`RunDir.declare_method_files`). A name registered again is replaced (a
    module reloaded), and its class names it as `name`. The built-in methods come first."""

    def add(cls: type[M]) -> type[M]:
        if name in MODES:
            raise ValueError(f"{name!r} is a geometry mode of fit, not a method's name")
        _load_built_in()
        cls.name = name
        _METHODS[name] = cls()
        RunDir.declare_method_files(_files())
        return cls

    return add


def unregister(name: str) -> None:
    """Remove a method (a test's own), and its files from a run's markers."""
    _METHODS.pop(name, None)
    RunDir.declare_method_files(_files())


def _files() -> tuple[str, ...]:
    return tuple(f for method in _METHODS.values() for f in method.files)


def _load_built_in() -> None:
    global _loaded
    if not _loaded:
        _loaded = True
        for module in BUILT_IN:
            importlib.import_module(module)


def names() -> tuple[str, ...]:
    """The registered methods' names, the built-in ones first."""
    _load_built_in()
    return tuple(_METHODS)


def get(name: str) -> GeometryMethod:
    """The method registered as `name`; a ValueError naming the registered ones for another."""
    _load_built_in()
    try:
        return _METHODS[name]
    except KeyError:
        raise ValueError(f"unknown geometry method {name!r}: the methods are {', '.join(_METHODS) or 'none'}"
                         ) from None


def fit_modes() -> tuple[str, ...]:
    """What `fit --geometry` takes: auto, a method's name, or given."""
    return (MODES[0], *names(), MODES[1])


def seed_keys() -> tuple[str, ...]:
    """The config keys of the methods' seeds (for a batch's runs)."""
    return tuple(m.seed_key for m in (get(n) for n in names()) if m.seed_key)


def method_files() -> tuple[str, ...]:
    """Every registered method's own file names in a run."""
    _load_built_in()
    return _files()
