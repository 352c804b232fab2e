"""The feature grid's lookup as one compiled CPU kernel (grid_kernel.c), with a torch fallback.

The torch lookup (`fields.DenseGrid.forward_torch`, `fields.trilinear`) builds the 8 corner weights and their
gradients as broadcast products, gathers the corners, blends them with a batched matrix product and
scatters the gradient back: a dozen passes over arrays eight times the size of the batch, which took
over half of a NeuS step on a photographed capture. The kernel does each point and level in one
pass, and its backward adds straight into the table's gradient.

It is compiled on first use with the system's C compiler into the user's cache folder
(`$XDG_CACHE_HOME/vq-mitsuba`, keyed by the source's hash) and loaded with ctypes. Where that cannot
be done (no compiler), on other devices or dtypes, and when the points need a gradient, the torch
lookup runs instead: the same arithmetic (tests/geometry/test_geometry.py compares the two).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("grid_kernel.c")
MAX_FEATURES = 16  # as grid_kernel.c

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_tried = False
_reason = "not loaded yet"


def _cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "vq-mitsuba"


def _compile(target: Path) -> None:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise RuntimeError("no C compiler (cc, gcc or clang) on PATH")
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        for openmp in (["-fopenmp"], []):  # serial where the compiler has no OpenMP
            proc = subprocess.run([cc, "-O3", "-shared", "-fPIC", "-std=gnu99", *openmp, str(SOURCE), "-o", tmp, "-lm"],
                                  capture_output=True, text=True)
            if proc.returncode == 0:
                break
        else:
            raise RuntimeError(f"{Path(cc).name} failed: {proc.stderr.strip()[-500:]}")
        os.replace(tmp, target)  # atomic: a concurrent process sees the old file or the whole new one
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _load() -> ctypes.CDLL | None:
    """The compiled kernel, compiling it once per source version; None (with the reason in
    `status()`) where that cannot be done."""
    global _lib, _tried, _reason
    with _lock:
        if _tried:
            return _lib
        _tried = True
        digest = hashlib.sha256(SOURCE.read_bytes()).hexdigest()[:16]
        target = _cache_dir() / f"grid_kernel-{digest}-{sys.platform}-{os.uname().machine}.so"
        try:
            if not target.is_file():
                try:
                    _compile(target)
                except PermissionError:  # an unwritable cache: a private temporary one
                    target = Path(tempfile.mkdtemp()) / target.name
                    _compile(target)
            lib = ctypes.CDLL(str(target))
        except (OSError, RuntimeError) as exc:
            _reason = f"torch lookup: the kernel could not be built ({exc})"
            return None
        p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
        lib.grid_forward.argtypes = [p, i64, p, i64, i64, p, p, p, i64, p, p, p, i32]
        lib.grid_backward.argtypes = [i64, i64, p, i64, i64, p, p, p, i64, p, p, p, p, i32]
        lib.grid_forward.restype = lib.grid_backward.restype = i32
        _lib, _reason = lib, "compiled kernel"
        return _lib


def status() -> str:
    """How the grid is looked up on the CPU: 'compiled kernel' or why the torch lookup runs."""
    _load()
    return _reason


def usable(table: torch.Tensor, points: torch.Tensor, features: int) -> bool:
    """Whether the kernel can do this lookup: float32 CPU tensors, points that need no gradient."""
    return (table.device.type == "cpu" and points.device.type == "cpu" and table.dtype == torch.float32
            and points.dtype == torch.float32 and not points.requires_grad and features <= MAX_FEATURES
            and _load() is not None)


class Layout:
    """A grid's shape for the kernel: resolution, first table row and hashed flag per level."""

    def __init__(self, res: list[int], offsets: list[int], hashed: list[bool], hash_mask: int):
        self.levels = len(res)
        self.res = torch.tensor(res, dtype=torch.int64, device="cpu")  # the kernel runs on the CPU only
        self.offsets = torch.tensor(offsets, dtype=torch.int64, device="cpu")
        self.hashed = torch.tensor([int(h) for h in hashed], dtype=torch.uint8, device="cpu")
        self.hash_mask = int(hash_mask)


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _forward(table, points, layout: Layout, level_weights, jacobian: bool):
    n, features = len(points), table.shape[1]
    feats = torch.empty(n, layout.levels * features, device="cpu")
    jac = torch.empty(n, layout.levels * features, 3, device="cpu") if jacobian else None
    code = _lib.grid_forward(_ptr(table), features, _ptr(points), n, layout.levels, _ptr(layout.res),
                             _ptr(layout.offsets), _ptr(layout.hashed), layout.hash_mask, _ptr(level_weights),
                             _ptr(feats), _ptr(jac), torch.get_num_threads())
    if code:
        raise RuntimeError(f"grid_forward failed ({code})")
    return feats, jac


class _Lookup(torch.autograd.Function):
    """Features (and their Jacobian in the points) of a grid table at data points; the gradient
    flows to the table only."""

    @staticmethod
    def forward(ctx, table, points, layout, level_weights, jacobian):
        feats, jac = _forward(table, points, layout, level_weights, jacobian)
        ctx.save_for_backward(points, level_weights)
        ctx.layout, ctx.shape = layout, table.shape
        if jacobian:
            return feats, jac
        return feats

    @staticmethod
    def backward(ctx, grad_feats, grad_jac=None):
        points, level_weights = ctx.saved_tensors
        layout = ctx.layout
        grad_table = torch.empty(ctx.shape, device="cpu")  # the kernel zeroes it
        gf = (torch.zeros(len(points), layout.levels * ctx.shape[1], device="cpu") if grad_feats is None
              else grad_feats.contiguous())
        gj = None if grad_jac is None else grad_jac.contiguous()
        code = _lib.grid_backward(ctx.shape[0], ctx.shape[1], _ptr(points), len(points), layout.levels, _ptr(layout.res),
                                  _ptr(layout.offsets), _ptr(layout.hashed), layout.hash_mask, _ptr(level_weights),
                                  _ptr(gf), _ptr(gj), _ptr(grad_table), torch.get_num_threads())
        if code:
            raise RuntimeError(f"grid_backward failed ({code})")
        return grad_table, None, None, None, None


def lookup(table: torch.Tensor, points: torch.Tensor, layout: Layout, level_weights: torch.Tensor,
           jacobian: bool = False):
    """Features (N, L * F) of `table` (rows, F) at points (N, 3) in [-1, 1]^3, each level scaled by
    its weight, and with `jacobian` their derivatives in the points (N, L * F, 3). Call only where
    `usable` says so."""
    points = points.contiguous()
    level_weights = level_weights.to(torch.float32).contiguous()
    if not table.is_contiguous():
        table = table.contiguous()
    if table.requires_grad and torch.is_grad_enabled():
        return _Lookup.apply(table, points, layout, level_weights, jacobian)
    with torch.no_grad():
        feats, jac = _forward(table.detach(), points, layout, level_weights, jacobian)
    return (feats, jac) if jacobian else feats
