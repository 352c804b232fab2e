"""The command line is thin: one module per command, one parser built from shared parents (each
option defined once, each with a one-line help), and `fit` is one library call that refuses a
fitted or edited run before any geometry work."""

import argparse
import ast
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from vq_mitsuba import cli
from vq_mitsuba.errors import InputError

# Which commands take -o and --quiet (from the shared parents).
OUTPUT = {"fit", "geometry", "pose", "render", "edit", "export", "eval", "make-scene", "batch"}
QUIET = {"fit", "geometry", "pose", "render", "export", "eval", "batch"}
DEVICE = {"fit", "geometry", "render", "eval", "export", "ui", "batch"}  # the commands that compute
CONFIG = {"fit", "geometry", "batch"}  # --preset, --config, --set, --help-config of the config system


def _subparsers(parser: argparse.ArgumentParser | None = None) -> dict[str, argparse.ArgumentParser]:
    parser = parser or cli.build_parser()
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices


def _replace_command(monkeypatch, command: str, func) -> None:
    """`cli.main` runs `func` for `command`, the parser otherwise as built."""
    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    _subparsers(parser)[command].set_defaults(func=func)


def _option(parser: argparse.ArgumentParser, flag: str):
    return parser._option_string_actions.get(flag)


def test_every_command_has_the_shared_options_where_expected():
    subs = _subparsers()
    assert set(subs) == {"fit", "geometry", "pose", "render", "edit", "export", "ui", "eval", "make-scene", "batch"}
    for name, parser in subs.items():
        out = _option(parser, "-o")
        assert (out is not None) == (name in OUTPUT), name
        if out is not None:
            assert out.option_strings == ["-o", "--output"] and out.dest == "output", name
        assert (_option(parser, "--quiet") is not None) == (name in QUIET), name
        assert _option(parser, "--threads") is not None, name
        assert (_option(parser, "--device") is not None) == (name in DEVICE), name
    # One definition, shared: every command's --quiet and --threads are the same argparse action.
    assert len({id(_option(subs[n], "--quiet")) for n in QUIET}) == 1
    assert len({id(_option(p, "--threads")) for p in subs.values()}) == 1
    assert len({id(_option(subs[n], "--device")) for n in DEVICE}) == 1
    for flag in ("--preset", "--config", "--set", "--help-config", "--downscale"):
        assert len({id(_option(subs[n], flag)) for n in CONFIG}) == 1, flag
    for flag in ("--holdout", "--resume"):  # the options of a capture read into one run
        assert len({id(_option(subs[n], flag)) for n in ("fit", "geometry")}) == 1, flag
    assert subs["export"]._option_string_actions["-o"].required


def test_every_option_has_a_one_line_help():
    for name, parser in _subparsers().items():
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            label = f"{name} {'/'.join(action.option_strings) or action.dest}"
            assert action.help and action.help.strip(), label
            assert "\n" not in action.help and len(action.help) <= 100, label


def test_fit_help_names_every_capture_format_as_the_format_describes_itself(capsys, monkeypatch):
    from vq_mitsuba.data.formats import FORMATS

    monkeypatch.setenv("COLUMNS", "60")  # wrapped narrow, a name stays whole (NeRF-synthetic)
    with pytest.raises(SystemExit):
        cli.main(["fit", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    missing = [fmt.DESCRIPTION for fmt in FORMATS if fmt.DESCRIPTION not in text]
    assert not missing, missing


def test_help_config_lines_fit_a_reader(capsys):
    assert cli.main(["fit", "--help-config"]) == 0
    long = [line for line in capsys.readouterr().out.splitlines() if len(line) > 200]
    assert not long, long


@pytest.mark.parametrize("name", sorted(_subparsers()))
def test_help_of_every_command_prints(name, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main([name, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: vq-mitsuba {name}")
    if name in OUTPUT:
        assert "-o OUT" in out or "-o NEW_RUN" in out


def test_cli_defines_each_option_once_in_small_functions():
    trees = [ast.parse(path.read_text()) for path in Path(cli.__file__).parent.glob("*.py")]
    flags = [node.args[0].value for tree in trees for node in ast.walk(tree) if isinstance(node, ast.Call)
             and getattr(node.func, "attr", None) == "add_argument" and node.args
             and isinstance(node.args[0], ast.Constant)]
    for flag in ("-o", "--quiet", "--threads", "--config", "--help-config", "--downscale", "--resume"):
        assert flags.count(flag) == 1, flag
    long = [(f.name, f.end_lineno - f.lineno + 1) for tree in trees for f in ast.walk(tree)
            if isinstance(f, ast.FunctionDef) and f.end_lineno - f.lineno + 1 > 60]
    assert not long, long


def test_each_command_is_one_module_with_its_parser_and_handler():
    """`cli/<command>.py` for each command: `add_parser` and `run`, and no library import at the
    top (the handler imports its library when it runs) but the BRDF inputs' declaration, which
    help texts name and which imports nothing of the package."""
    folder = Path(cli.__file__).parent
    allowed = {"vq_mitsuba.cli.common", "vq_mitsuba.errors", "vq_mitsuba.brdf"}
    for name in _subparsers():
        path = folder / f"{name.replace('-', '_')}.py"
        tree = ast.parse(path.read_text())
        top = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        assert {"add_parser", "run"} <= top, name
        imported = [f"{n.module}.{a.name}" if n.module == "vq_mitsuba" else n.module
                    for n in tree.body if isinstance(n, ast.ImportFrom) and n.module.startswith("vq_mitsuba")
                    for a in n.names]
        assert set(imported) <= allowed, (name, imported)
    brdf_imports = [n for n in ast.parse((folder.parent / "brdf.py").read_text()).body
                    if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert all(isinstance(n, ast.ImportFrom) and n.module in ("__future__", "dataclasses") for n in brdf_imports)


def _capture_without_geometry(folder: Path) -> Path:
    """A transforms json with no mesh beside it: `fit` would reconstruct the geometry with NeuS."""
    folder.mkdir(parents=True)
    path = folder / "transforms_train.json"
    path.write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    return path


@pytest.fixture
def no_geometry_stage(monkeypatch):
    """The geometry stage fails the test if it is reached."""
    import vq_mitsuba.engine.pipeline as pipeline
    import vq_mitsuba.geometry.stage as geometry

    def fail(*args, **kwargs):
        raise AssertionError("the geometry stage ran")

    monkeypatch.setattr(pipeline, "ensure_geometry", fail)
    monkeypatch.setattr(geometry, "run_geometry", fail)


def test_fit_capture_refuses_a_fitted_run_before_neus(tmp_path, no_geometry_stage, capsys):
    from vq_mitsuba.config import load_config
    from vq_mitsuba.data.captures import open_capture
    from vq_mitsuba.engine.pipeline import fit_capture, needs_reconstruction
    from vq_mitsuba.run.run_dir import RunDir

    capture = _capture_without_geometry(tmp_path / "cap")
    assert needs_reconstruction(open_capture(capture))
    run = RunDir(tmp_path / "run")
    run.create()
    (run / RunDir.CHECKPOINT).write_bytes(b"a fitted run")
    with pytest.raises(InputError, match="already holds a fitted run"):
        fit_capture(capture, run.dir, load_config(None, []))
    with pytest.raises(InputError, match="already holds a fitted run"):
        fit_capture(capture, run.dir, load_config(None, []), geometry="neus")
    assert cli.main(["fit", str(capture), "-o", str(run.dir), "--quiet"]) == 2
    assert "already holds a fitted run" in capsys.readouterr().err
    assert sorted(p.name for p in run.dir.iterdir()) == [RunDir.CHECKPOINT]


def test_fit_capture_refuses_an_edited_run_and_other_files_before_neus(tmp_path, no_geometry_stage):
    from vq_mitsuba.config import load_config
    from vq_mitsuba.engine.pipeline import fit_capture
    from vq_mitsuba.run.run_dir import RunDir

    capture = _capture_without_geometry(tmp_path / "cap")
    edited = RunDir(tmp_path / "edited")
    edited.create()
    edited.write_info({"capture": str(capture), "world": "blender", "envmap_to_world": np.eye(4).tolist(),
                       "edit_of": {"relative": "../run", "absolute": str(tmp_path / "run")}})
    with pytest.raises(InputError, match="holds an edited run"):
        fit_capture(capture, edited.dir, load_config(None, []))
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="no vq-mitsuba run"):
        fit_capture(capture, mine, load_config(None, []))
    with pytest.raises(InputError, match="--geometry neus"):
        fit_capture(capture, tmp_path / "new", load_config(None, []), geometry="neus", mesh=tmp_path / "m.ply")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("value", ["2,0,0", "0.5,0.5", "red"])
def test_background_color_errors_name_the_option(tmp_path, capsys, value):
    run = tmp_path / "run"
    assert cli.main(["fit", str(tmp_path / "scene.xml"), "-o", str(run), "--background-color", value]) == 2
    err = capsys.readouterr().err
    assert f"error: --background-color {value}: capture.background_color must be R,G,B" in err
    assert "--set" not in err and not run.exists()


def test_library_warnings_are_one_line_each(monkeypatch, capsys):
    """A PIL warning is shown once as `warning: ...` (no source line, however often it comes);
    scikit-learn's k-means note about duplicate points is not shown."""
    import io

    import numpy as np
    from PIL import Image

    def command(args):
        palette = Image.new("P", (4, 4))
        palette.putpalette([0, 0, 0, 255, 0, 0] + [0] * 762)
        buffer = io.BytesIO()
        palette.save(buffer, format="PNG", transparency=b"\x00\x80")  # tRNS as bytes: PIL warns on convert
        for _ in range(2):
            Image.open(io.BytesIO(buffer.getvalue())).convert("RGB")
        from sklearn.cluster import KMeans

        KMeans(n_clusters=3, n_init=1).fit(np.zeros((10, 2)))
        return 0

    _replace_command(monkeypatch, "make-scene", command)
    assert cli.main(["make-scene", "demo"]) == 0
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["warning: Palette images with Transparency expressed in bytes should be converted to RGBA images"]


def test_geometry_is_refused_while_another_process_writes_the_run(tmp_path, no_geometry_stage, capsys):
    import signal
    import subprocess
    import sys

    capture = _capture_without_geometry(tmp_path / "cap")
    run = tmp_path / "run"
    code = ("import sys, time\nfrom vq_mitsuba.run.run_dir import RunDir\n"
            "with RunDir(sys.argv[1]).lock('fit'):\n    print('held', flush=True)\n    time.sleep(600)\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert cli.main(["geometry", str(capture), "-o", str(run), "--quiet"]) == 2
        assert f"{run}: is in use by `vq-mitsuba fit` (pid {holder.pid} on " in capsys.readouterr().err
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()


def _help_text(parser: argparse.ArgumentParser) -> str:
    return " ".join(parser.format_help().split())  # argparse's line breaks joined


def test_help_says_what_the_commands_do():
    """The help texts hold what the code does: no command that reads a capture says NeuS needs
    masks (it runs without them), `fit` names every file it writes, `render --envmap` takes .hdr,
    `eval` names its held-out mode and `--mesh` is for any posed capture."""
    from vq_mitsuba.run.run_dir import RunDir

    subs = _subparsers()
    for name, parser in subs.items():
        text = _help_text(parser).lower()
        assert "needs alpha masks" not in text and "with alpha masks" not in text, name
        assert "masked images" not in text, name
    fit = _help_text(subs["fit"])
    for file in (RunDir.INFO, RunDir.CONFIG, RunDir.CHECKPOINT, RunDir.MESH, RunDir.ENVMAP, RunDir.MATERIALS,
                 RunDir.ERR_PLOT, RunDir.SHEET, RunDir.LOSS_PLOT, RunDir.FIT, RunDir.RESIDUAL):
        assert file in fit, file
    assert "NeRF" not in _option(subs["fit"], "--mesh").help
    assert ".hdr" in _option(subs["render"], "--envmap").help
    assert "render.json" in _help_text(subs["render"])
    eval_help = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert "held-out" in next(c.help for c in eval_help._choices_actions if c.dest == "eval")


@pytest.mark.parametrize("command, hint", [("fit", True), ("geometry", True), ("render", False), ("eval", False)])
def test_ctrl_c_hints_at_resume_only_where_a_command_resumes(monkeypatch, capsys, tmp_path, command, hint):
    def interrupted(args):
        raise KeyboardInterrupt

    _replace_command(monkeypatch, command, interrupted)
    run = tmp_path / "run"
    run.mkdir()  # the run folder the command had begun to write
    argv = {"fit": ["fit", "cap", "-o", str(run)], "geometry": ["geometry", "cap", "-o", str(run)],
            "render": ["render", "run", "--cameras", "c"], "eval": ["eval", "run"]}[command]
    assert cli.main(argv) == 130
    err = capsys.readouterr().err
    assert err.startswith("interrupted")
    assert ("--resume" in err) == hint and (f"vq-mitsuba {command}" in err) == hint
    if hint:  # stopped before its run folder existed: nothing to resume
        run.rmdir()
        assert cli.main(argv) == 130
        err = capsys.readouterr().err
        assert "nothing was kept yet" in err and "without --resume" in err


def test_a_signal_whose_exception_a_library_lost_still_ends_the_command_as_a_stop(monkeypatch, capsys):
    """SIGTERM arriving where its exception is dropped (here a finaliser; in a fit, Dr.Jit's import
    of a torch tensor): the command's work ends, and it exits 143 as a stopped command, not 0."""
    import signal

    from test_loop import SignalInFinaliser

    def work(args):
        SignalInFinaliser()
        return 0

    monkeypatch.setattr(sys, "unraisablehook", lambda unraisable: None)  # the dropped exception, unreported
    _replace_command(monkeypatch, "eval", work)
    assert cli.main(["eval", "run"]) == 128 + signal.SIGTERM
    assert capsys.readouterr().err.startswith("interrupted")
    _replace_command(monkeypatch, "eval", lambda args: 0)
    assert cli.main(["eval", "run"]) == 0  # the next command starts with no signal pending


def test_the_tools_own_warnings_go_to_stderr(monkeypatch, capsys):
    """A warning of vq-mitsuba's own (errors.warn) is one `warning:` line on stderr, never on stdout
    among a command's results."""
    from vq_mitsuba.errors import warn

    def warns(args):
        warn("the mesh is tiny")
        print("result")
        return 0

    _replace_command(monkeypatch, "eval", warns)
    assert cli.main(["eval", "run"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "result\n" and captured.err == "warning: the mesh is tiny\n"


def test_the_command_line_manual_is_current():
    """docs/cli.md is `python -m vq_mitsuba.cli --manual > docs/cli.md`: regenerate it."""
    doc = Path(__file__).resolve().parents[2] / "docs" / "cli.md"
    assert doc.read_text() == cli.manual()
    assert all(f"## `vq-mitsuba {name}`" in doc.read_text() for name in _subparsers())


def test_a_fit_checks_its_folder_and_poses_once(tmp_path, monkeypatch):
    """`fit` runs in one module (engine/pipeline.py): the run folder is checked once and an unposed
    capture is posed once per fit, and no other module calls either step."""
    import vq_mitsuba.engine.pipeline as fit_module
    from vq_mitsuba.config import load_config
    from vq_mitsuba.run.run_dir import RunDir

    calls = []
    check = fit_module.check_fit_target
    monkeypatch.setattr(fit_module, "check_fit_target", lambda *a: calls.append("check") or check(*a))
    monkeypatch.setattr(fit_module.CaptureSource, "posed", property(lambda capture: False))  # photos, say
    monkeypatch.setattr(fit_module, "ensure_poses", lambda capture, run, *a, **k: calls.append("poses") or capture)
    monkeypatch.setattr(fit_module, "ensure_geometry", lambda capture, run, *a, **k: run / RunDir.MESH)
    monkeypatch.setattr(fit_module, "fit_materials", lambda *a, **k: {"iterations": 1})
    capture = _capture_without_geometry(tmp_path / "cap")
    fit_module.fit_capture(capture, tmp_path / "run", load_config(None, []), log=lambda line: None)
    assert calls == ["check", "poses"]
    package = Path(cli.__file__).resolve().parent.parent
    callers = {str(path.relative_to(package)) for path in package.rglob("*.py") for node in ast.walk(ast.parse(
        path.read_text())) if isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("ensure_poses",
                                                                                                "check_fit_target")}
    assert callers == {"engine/pipeline.py"}, callers


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="a GPU machine has CUDA")
def test_device_cuda_without_cuda_is_refused_naming_the_missing_half(tmp_path, capsys):
    assert cli.main(["render", str(tmp_path), "--cameras", str(tmp_path / "none.json"), "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert "--device cuda" in err and "torch sees no CUDA device" in err
    from vq_mitsuba.backend import choose_device, torch_device

    assert choose_device("cpu") == "cpu" and torch_device().type == "cpu"
