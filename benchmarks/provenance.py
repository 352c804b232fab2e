"""Where a benchmark result comes from, and writing it: one module for every script here.

    from provenance import command_line, describe, provenance, write_result

    write_result(out / f"load_{provenance()['commit']}.json", {"seconds": 15, "results": results})
    print(describe())

`provenance()` is the block every result JSON starts with (top-level keys, as the results in
benchmarks/results/ have them):

- `command`: the command line, `python benchmarks/SCRIPT.py ARGS` (`command_line`);
- `commit`: short hash of HEAD of this checkout ("unknown" outside git); `dirty`: whether
  `git status --porcelain` lists anything (modified, staged, deleted or untracked files);
  `dirty_files`: those entries as git prints them (`" M path"`, `"?? path"`). The state is read
  once, when this module is imported, i.e. when the script starts: the code that ran;
- `date`: UTC time of the call (ISO 8601, seconds);
- `machine`: `cpu` (model name), `cores` (`os.cpu_count()`), `cores_usable` (the process's CPU
  affinity), `memory_gb` (MemTotal), `gpu` (names from nvidia-smi, else torch's CUDA devices;
  null when none), `torch_cuda` (torch.cuda.is_available() when torch is loaded, else null), `os`;
- `versions`: `python`, `mitsuba`, `mitsuba_variant` (when mitsuba is loaded and a variant set),
  `drjit`, `torch`, `numpy` (null when not installed), and `scikit-image`, `trimesh`, `pymeshlab`,
  `vq_mitsuba` when installed.

Nothing here imports torch, mitsuba or vq_mitsuba (versions come from the installed packages'
metadata): importing torch early changes OpenMP's wait policy, which `bench_load.py` measures.

`write_result(path, data)` writes `{**provenance(), **data}` as JSON atomically (a temporary file
in the same folder, then a rename): a reader or an interrupted run never sees half a file. A key
of `data` wins over the block's (e.g. a `command` with a note, or a block taken earlier with
`{**provenance(), ...}` so that a markdown report and the JSON agree). It is its own writer, not
`vq_mitsuba.run.run_dir.write_atomic` (run files), which would import torch.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import uuid
from functools import lru_cache
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CORE_PACKAGES = ("mitsuba", "drjit", "torch", "numpy")  # always in `versions` (null when missing)
MORE_PACKAGES = ("scikit-image", "trimesh", "pymeshlab", "vq_mitsuba")  # when installed


def _run(cmd: list[str], cwd: Path | None = None) -> str | None:
    """stdout of a short command, or None when it cannot run or fails."""
    try:
        res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    return res.stdout if res.returncode == 0 else None


def git_state(root: Path = ROOT) -> dict:
    """{"commit": short hash or "unknown", "dirty": bool, "dirty_files": [porcelain entries]}."""
    commit = (_run(["git", "rev-parse", "--short", "HEAD"], root) or "").strip() or "unknown"
    status = _run(["git", "status", "--porcelain"], root)
    files = [line for line in (status or "").splitlines() if line.strip()]
    return {"commit": commit, "dirty": bool(files), "dirty_files": files}


_GIT = git_state()  # when the script starts: the code that runs


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo where there is one)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gb() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        pass
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        return None


@lru_cache(maxsize=None)
def _nvidia_smi_gpus() -> tuple[str, ...]:
    if not shutil.which("nvidia-smi"):
        return ()
    out = _run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"])
    return tuple(n.strip() for n in (out or "").splitlines() if n.strip())


def _gpus() -> tuple[str | None, bool | None]:
    """(GPU names or None, torch.cuda.is_available() when torch is already loaded, else None)."""
    names = list(_nvidia_smi_gpus())
    cuda = None
    torch = sys.modules.get("torch")
    if torch is not None:
        try:
            cuda = bool(torch.cuda.is_available())
            if cuda and not names:
                names = [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]
        except Exception:  # noqa: BLE001 - a broken CUDA set-up is recorded as no GPU
            cuda = False
    return (", ".join(names) or None), cuda


def machine() -> dict:
    gpu, cuda = _gpus()
    try:
        usable = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = os.cpu_count()
    return {"cpu": cpu_model(), "cores": os.cpu_count(), "cores_usable": usable, "memory_gb": _memory_gb(),
            "gpu": gpu, "torch_cuda": cuda, "os": platform.platform()}


@lru_cache(maxsize=None)
def _package_versions() -> dict:
    out = {}
    for name in CORE_PACKAGES + MORE_PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            if name in CORE_PACKAGES:
                out[name] = None
    return out


def _mitsuba_variant() -> str | None:
    mi = sys.modules.get("mitsuba")  # only when the script loaded it: no import here
    if mi is None:
        return None
    try:
        return mi.variant() or None
    except Exception:  # noqa: BLE001 - no variant set yet
        return None


def versions() -> dict:
    pkgs = _package_versions()
    out = {"python": platform.python_version(), "mitsuba": pkgs["mitsuba"]}
    variant = _mitsuba_variant()
    if variant:
        out["mitsuba_variant"] = variant
    out.update((k, v) for k, v in pkgs.items() if k != "mitsuba")
    return out


def command_line(argv: list[str] | None = None, script: str | os.PathLike | None = None) -> str:
    """`python SCRIPT ARGS`: the script (sys.argv[0] unless given; relative to the repository when
    inside it) and its arguments (sys.argv[1:] unless `argv` is given), quoted for a shell."""
    script = Path(script if script is not None else (sys.argv[0] if sys.argv and sys.argv[0] else "-c"))
    try:
        shown = str(script.resolve().relative_to(ROOT)) if script.is_file() else str(script)
    except (ValueError, OSError):
        shown = str(script)
    args = list(sys.argv[1:] if argv is None else argv)
    return shlex.join(["python", shown, *args])


def provenance(command: str | None = None) -> dict:
    """The provenance block: command, commit, dirty, dirty_files, date, machine, versions."""
    return {"command": command if command is not None else command_line(),
            **_GIT, "dirty_files": list(_GIT["dirty_files"]),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "machine": machine(), "versions": versions()}


def describe(record: dict | None = None) -> str:
    """One line for a log or a markdown report: commit, machine, versions, date (of `record`, a
    result with the provenance keys, or of this process now). Older results, which keep the commit
    and the versions inside "machine", read too."""
    r = record if record is not None else provenance()
    m = r.get("machine") or {}
    v = {**m, **(r.get("versions") or {})}
    commit = str(r.get("commit") or m.get("commit") or "?")
    if r.get("dirty"):
        commit += f" (dirty: {len(r.get('dirty_files') or [])} files)"
    mem = f", {m['memory_gb']:g} GB" if m.get("memory_gb") is not None else ""
    cores = m.get("cores")
    if m.get("cores_usable") not in (None, cores):
        cores = f"{m['cores_usable']} of {cores}"
    mitsuba = v.get("mitsuba")
    if v.get("mitsuba_variant"):
        mitsuba = f"{mitsuba} ({v['mitsuba_variant']})"
    return (f"commit {commit}; {m.get('cpu', '?')}, {cores} cores{mem}, GPU {m.get('gpu') or 'none'}; "
            f"python {v.get('python')}, mitsuba {mitsuba}, drjit {v.get('drjit')}, torch {v.get('torch')}, "
            f"numpy {v.get('numpy')}; {r.get('date', '?')}")


def write_json(path: str | os.PathLike, data, *, indent: int | None = 2) -> Path:
    """`data` as JSON at `path`, atomically: written to a temporary file beside it, then renamed
    over it (an interrupted write leaves the old file, never half a new one)."""
    path = Path(path)
    text = json.dumps(data, indent=indent) + "\n"  # serialised first: an error leaves no file behind
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "x") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_result(path: str | os.PathLike, data: dict, *, indent: int | None = 2) -> Path:
    """`data` with the provenance block in front (keys of `data` win), written atomically."""
    return write_json(path, {**provenance(), **data}, indent=indent)


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="Print this checkout's and machine's provenance (one line, or the "
                                            "JSON block with --json).")
    p.add_argument("--json", action="store_true", help="print the whole block as JSON")
    args = p.parse_args(argv)
    print(json.dumps(provenance(), indent=2) if args.json else describe())
    return 0


if __name__ == "__main__":
    sys.exit(main())
