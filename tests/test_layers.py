"""The package's layers import one way, in the order of LAYERS below (docs/method.md's layout lists
them in it), and rendering a finished run imports no training code."""

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "vq_mitsuba"
# Each layer may import its own and the lower ones. `run` (the run folder and the loop skeleton) sits
# below every stage that writes a run, the geometry stage included; synthetic (the make-scene
# datasets) and cli sit on top. Base modules (config, errors, backend, compiled, brdf, messages) are below all.
LAYERS = [{"config", "errors", "backend", "compiled", "brdf", "messages"}, {"data"}, {"models"}, {"run"}, {"geometry"}, {"render"}, {"engine"},
          {"eval", "edit", "export"}, {"ui"}, {"synthetic"}, {"batch"}, {"cli"}]


def _layer(module: str) -> int:
    top = module.split(".")[1] if module.count(".") else ""
    return next(i for i, names in enumerate(LAYERS) if top in names)


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("vq_mitsuba"):
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                out.add(full if (PACKAGE.parent / (full.replace(".", "/") + ".py")).is_file() else node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("vq_mitsuba")}
    return out


def _module(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    return ".".join(p for p in rel.parts if p != "__init__")


def test_no_upward_import_and_no_cycle():
    graph = {}
    for path in PACKAGE.rglob("*.py"):
        if path.name == "cycles_worker.py":  # runs inside Blender's interpreter, imports nothing of ours
            continue
        graph[_module(path)] = {m for m in _imports(path) if m != "vq_mitsuba"}
    upward = [(m, i) for m, deps in graph.items() if m != "vq_mitsuba" for i in deps if _layer(i) > _layer(m)]
    assert not upward, upward
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for d in graph.get(m, ()):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack + [m, d]))
            if d not in state:
                visit(d, stack + [m])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [])


def test_render_command_imports_no_training_code(tmp_path):
    code = ("import sys\nfrom vq_mitsuba import cli\n"
            "try:\n    cli.main(['render', sys.argv[1], '--cameras', sys.argv[1] + '/none.json', '--quiet'])\n"
            "except SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('vq_mitsuba')))")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True, check=True)
    loaded = eval(out.stdout.strip().splitlines()[-1])
    assert "vq_mitsuba.run.run_dir" in loaded and "vq_mitsuba.render.views" in loaded
    # NeuS's package and its registration as a geometry method (the CLI's --geometry choices) import no
    # training code; its rooms do
    registration = {"vq_mitsuba.geometry.neus", "vq_mitsuba.geometry.neus.method"}
    assert not [m for m in loaded if m.startswith(("vq_mitsuba.engine", "vq_mitsuba.geometry.neus"))
                and m not in registration], loaded


def test_only_run_dir_names_run_files():
    """Every JSON and torch file of a run folder is named once, in RunDir, or, for a geometry method's
    own files (its checkpoint), once in the method's package: no other module spells one out.
    (mesh.ply is also a capture's file name, so the capture loaders may say it.)"""
    import inspect

    from vq_mitsuba.geometry import methods
    from vq_mitsuba.run.run_dir import RunDir

    names = {v for k, v in vars(RunDir).items() if k.isupper() and isinstance(v, str) and v.endswith((".json", ".pt"))}
    assert {"run.json", "checkpoint.pt", "geometry.json", "metrics.json"} <= names
    package_of = {f: Path(inspect.getfile(type(methods.get(n)))).resolve().parent
                  for n in methods.names() for f in methods.get(n).files}
    assert "neus.pt" in package_of
    found, own = [], {f: [] for f in package_of}
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Constant) and isinstance(node.value, str)):
                continue
            where = (str(path.relative_to(PACKAGE)), node.lineno, node.value)
            if node.value in names and path.name != "run_dir.py":
                found.append(where)
            elif node.value in own:
                inside = package_of[node.value] in path.resolve().parents
                (own[node.value] if inside else found).append(where)
    assert not found, found
    assert all(len(places) == 1 for places in own.values()), own


def test_one_basename_per_concept():
    """Outside cli/ (one module per command, named after it), no two modules share a file name."""
    names = [p.name for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" and "cli" not in p.relative_to(PACKAGE).parts]
    assert sorted({n for n in names if names.count(n) > 1}) == []
