"""benchmarks/provenance.py: the provenance block of every benchmark result, and its atomic writer."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.fixture(scope="module")
def prov():
    """benchmarks/provenance.py, loaded from its file (benchmarks/ is scripts, not a package)."""
    spec = importlib.util.spec_from_file_location("benchmarks_provenance", BENCHMARKS / "provenance.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    yield module
    sys.modules.pop(spec.name, None)


def test_block_has_the_keys(prov):
    block = prov.provenance()
    assert {"command", "commit", "dirty", "dirty_files", "date", "machine", "versions"} <= set(block)
    assert isinstance(block["dirty"], bool)
    assert isinstance(block["dirty_files"], list) and all(isinstance(f, str) for f in block["dirty_files"])
    assert block["dirty"] == bool(block["dirty_files"])
    assert isinstance(block["commit"], str) and block["commit"]
    assert {"cpu", "cores", "memory_gb", "gpu", "os"} <= set(block["machine"])
    assert {"python", "mitsuba", "drjit", "torch", "numpy"} <= set(block["versions"])
    assert block["command"].startswith("python ")
    json.dumps(block)  # all of it serialisable


def test_command_line_quotes_and_takes_argv(prov):
    line = prov.command_line(["--scenes", "demo", "a b"], BENCHMARKS / "bench_scenes.py")
    assert line == "python benchmarks/bench_scenes.py --scenes demo 'a b'"


def test_describe_is_one_line(prov):
    line = prov.describe()
    assert "\n" not in line and prov.provenance()["commit"] in line
    # an older result (commit and versions inside "machine") reads too
    old = {"date": "d", "machine": {"commit": "abc1234-dirty", "cpu": "c", "cores": 2, "mitsuba": "3.9.1"}}
    assert "abc1234-dirty" in prov.describe(old) and "mitsuba 3.9.1" in prov.describe(old)


def test_write_result_is_atomic_json_with_the_block(prov, tmp_path):
    path = tmp_path / "out" / "result.json"
    written = prov.write_result(path, {"command": "python x.py --note", "rows": [1, 2]})
    assert written == path
    record = json.loads(path.read_text())
    assert record["rows"] == [1, 2] and record["command"] == "python x.py --note"  # the data's keys win
    assert isinstance(record["dirty"], bool) and "machine" in record and "versions" in record
    prov.write_result(path, {"rows": [3]})  # over an existing file
    assert json.loads(path.read_text())["rows"] == [3]
    with pytest.raises(TypeError):
        prov.write_result(path, {"rows": object()})  # not serialisable: the old file stays
    assert json.loads(path.read_text())["rows"] == [3]
    assert [p.name for p in path.parent.iterdir()] == ["result.json"]  # no temporary file left


def test_no_benchmark_script_patches_sys_path():
    patched = [p.name for p in sorted(BENCHMARKS.glob("*.py"))
               if re.search(r"sys\.path\.(insert|append)", p.read_text())]
    assert not patched, f"benchmark scripts patch sys.path (the package is installed): {patched}"
