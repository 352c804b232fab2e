#!/usr/bin/env python
"""Check: a refactor leaves every stage's output as it was. Two revisions fit the same small
bundled scene, once on its true mesh and once through NeuS from its images, on one thread
(one Dr.Jit worker, `neus.time_limit_s=0`: step counts, not the clock, end each stage), then render
its test views; every file of the two runs is compared.

    .venv/bin/python benchmarks/same_outputs.py --refs BASE HEAD [--scene demo] [--out benchmarks/out/same_outputs]

A file counts as the same when its bytes are; a JSON file when every value is but timings and
paths; a torch file (.pt) when every tensor and value of its state is but timings (a pickle's bytes
may differ for the same tensors). Prints each file that is not the same with what differs, and
writes OUT/same_outputs.json; exits 1 when any file differs.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from provenance import ROOT, describe, provenance, write_result

SETTINGS = ["train.iterations=120", "residual.iterations=60", "neus.time_limit_s=0", "neus.iterations=300"]
# keys whose values are clocks or places, not results (a leaf's own name)
VOLATILE = {"run", "command", "date", "started", "finished", "elapsed", "path", "dir", "host"}


def volatile(key: str) -> bool:
    """A clock or a place: the leaf's name, or a block of seconds ("seconds.train")."""
    parts = [p for p in re.split(r"[.\[\]]", key) if p]
    return parts[-1] in VOLATILE or parts[-1].endswith("_s") or \
        any(w in p for p in parts for w in ("seconds", "time", "version", "rate"))


def cli(tree: Path, *args: str) -> None:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    subprocess.run([sys.executable, "-m", "vq_mitsuba.cli", *args, "--threads", "1"], cwd=tree, env=env, check=True,
                   stdout=subprocess.DEVNULL)


def leaves(x, pre=""):
    """(dotted key, value) of every leaf of a nested dict / list."""
    if isinstance(x, dict):
        for k, v in x.items():
            yield from leaves(v, f"{pre}.{k}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            yield from leaves(v, f"{pre}[{i}]")
    else:
        yield pre, x


def _equal(x, y) -> bool:
    import numpy as np
    import torch

    if isinstance(x, torch.Tensor) or isinstance(y, torch.Tensor):
        return isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor) and x.dtype == y.dtype \
            and x.shape == y.shape and bool(torch.equal(x, y))
    try:
        return bool(np.all(np.asarray(x) == np.asarray(y)))
    except (ValueError, TypeError):
        return repr(x) == repr(y)


def differences(a: Path, b: Path) -> list[str]:
    """What differs between the file a and the file b, [] when they are the same."""
    x, y = a.read_bytes(), b.read_bytes()
    if x == y:
        return []
    if a.suffix == ".json":
        la, lb = dict(leaves(json.loads(x))), dict(leaves(json.loads(y)))
    elif a.suffix == ".pt":
        import torch

        la, lb = (dict(leaves(torch.load(p, map_location="cpu", weights_only=False))) for p in (a, b))
    else:
        return ["bytes"]
    keys = sorted(k for k in set(la) | set(lb) if k not in la or k not in lb or not _equal(la[k], lb[k]))
    return [k for k in keys if not volatile(k)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--refs", nargs=2, required=True, metavar=("BASE", "HEAD"), help="the two git revisions")
    ap.add_argument("--scene", default="demo", help="the bundled scene (make-scene NAME)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out" / "same_outputs", help="result folder")
    args = ap.parse_args()
    record = provenance()
    sets = [x for s in SETTINGS for x in ("--set", s)]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        trees = [tmp / f"rev{k}" for k in range(2)]
        for ref, tree in zip(args.refs, trees):
            subprocess.run(["git", "worktree", "add", "--detach", str(tree), ref], cwd=ROOT, check=True,
                           capture_output=True)
        try:
            data = tmp / "data"
            cli(trees[0], "make-scene", args.scene, "-o", str(data), "--resolution", "32", "--n-train", "8",
                "--n-test", "2", "--spp", "16")
            for tree in trees:
                runs = tmp / "runs" / tree.name
                cli(tree, "fit", str(data / "scene.xml"), "-o", str(runs / "mesh"), "--preset", "demo", "--quiet", *sets)
                cli(tree, "fit", str(data / "transforms_train.json"), "-o", str(runs / "neus"), "--preset", "demo",
                    "--geometry", "neus", "--quiet", *sets)
                cli(tree, "render", str(runs / "mesh"), "--cameras", str(data / "transforms_test.json"),
                    "-o", str(runs / "mesh" / "test_views"), "--quiet")
            a, b = (tmp / "runs" / t.name for t in trees)
            files = sorted({p.relative_to(a) for p in a.rglob("*") if p.is_file()}
                           | {p.relative_to(b) for p in b.rglob("*") if p.is_file()})
            result = {}
            for rel in files:
                pa, pb = a / rel, b / rel
                result[str(rel)] = (["missing"] if not (pa.is_file() and pb.is_file())
                                    else differences(pa, pb))
        finally:
            for tree in trees:
                subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True)
    different = {k: v for k, v in result.items() if v}
    print(describe(record))
    print(f"{len(files)} files, {len(files) - len(different)} the same ({args.refs[0]} against {args.refs[1]})")
    for rel, what in different.items():
        print(f"  {rel}: {', '.join(what[:8])}")
    write_result(args.out / "same_outputs.json", {**record, "refs": args.refs, "scene": args.scene,
                                                   "settings": SETTINGS, "files": result,
                                                   "same": not different})
    return 1 if different else 0


if __name__ == "__main__":
    raise SystemExit(main())
