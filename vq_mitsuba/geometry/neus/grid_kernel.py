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
            and (_lib if _tried else _load()) is not None)  # no lock once loaded: torch.compile traces this


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


def _forward(table, points, res, offsets, hashed, hash_mask: int, level_weights, jacobian: bool):
    n, features, levels = len(points), table.shape[1], len(res)
    feats = torch.empty(n, levels * features, device="cpu")
    jac = torch.empty(n, 3, levels * features, device="cpu") if jacobian else None
    code = _lib.grid_forward(_ptr(table), features, _ptr(points), n, levels, _ptr(res), _ptr(offsets), _ptr(hashed),
                             hash_mask, _ptr(level_weights), _ptr(feats), _ptr(jac), torch.get_num_threads())
    if code:
        raise RuntimeError(f"grid_forward failed ({code})")
    return feats, jac


# The lookup is a torch operator (torch.library), so that `torch.compile` keeps a step that calls it
# in one graph: the kernel is opaque to the compiler, its output shapes are declared by `_shapes`.
@torch.library.custom_op("vq_mitsuba::grid_lookup", mutates_args=(), device_types="cpu")
def _lookup_op(table: torch.Tensor, points: torch.Tensor, res: torch.Tensor, offsets: torch.Tensor,
               hashed: torch.Tensor, hash_mask: int, level_weights: torch.Tensor,
               jacobian: bool) -> tuple[torch.Tensor, torch.Tensor]:
    feats, jac = _forward(table.contiguous(), points.contiguous(), res, offsets, hashed, hash_mask,
                          level_weights.contiguous(), jacobian)
    return feats, jac if jacobian else feats.new_empty(0)


@_lookup_op.register_fake
def _shapes(table, points, res, offsets, hashed, hash_mask, level_weights, jacobian):
    k = res.shape[0] * table.shape[1]
    return points.new_empty(points.shape[0], k), points.new_empty((points.shape[0], 3, k) if jacobian else (0,))


@torch.library.custom_op("vq_mitsuba::grid_lookup_backward", mutates_args=(), device_types="cpu")
def _backward_op(rows: int, features: int, points: torch.Tensor, res: torch.Tensor, offsets: torch.Tensor,
                 hashed: torch.Tensor, hash_mask: int, level_weights: torch.Tensor, grad_feats: torch.Tensor,
                 grad_jac: torch.Tensor) -> torch.Tensor:
    grad_table = torch.empty(rows, features, device="cpu")  # the kernel zeroes it
    gf, gj = grad_feats.contiguous(), (grad_jac.contiguous() if grad_jac.numel() else None)
    code = _lib.grid_backward(rows, features, _ptr(points), len(points), len(res), _ptr(res), _ptr(offsets),
                              _ptr(hashed), hash_mask, _ptr(level_weights), _ptr(gf), _ptr(gj), _ptr(grad_table),
                              torch.get_num_threads())
    if code:
        raise RuntimeError(f"grid_backward failed ({code})")
    return grad_table


@_backward_op.register_fake
def _backward_shape(rows, features, points, res, offsets, hashed, hash_mask, level_weights, grad_feats, grad_jac):
    return grad_feats.new_empty(rows, features)


def _save(ctx, inputs, output):
    table, points, res, offsets, hashed, hash_mask, level_weights, jacobian = inputs
    ctx.save_for_backward(points, res, offsets, hashed, level_weights)
    ctx.hash_mask, ctx.rows, ctx.features, ctx.jacobian = hash_mask, table.shape[0], table.shape[1], jacobian


def _table_gradient(ctx, grad_feats, grad_jac):
    """The gradient flows to the table only (the points are data)."""
    points, res, offsets, hashed, level_weights = ctx.saved_tensors
    if grad_feats is None:
        grad_feats = points.new_zeros(len(points), len(res) * ctx.features)
    if grad_jac is None or not ctx.jacobian:
        grad_jac = points.new_empty(0)
    grad = _backward_op(ctx.rows, ctx.features, points, res, offsets, hashed, ctx.hash_mask, level_weights,
                        grad_feats, grad_jac)
    return grad, None, None, None, None, None, None, None


_lookup_op.register_autograd(_table_gradient, setup_context=_save)


def lookup(table: torch.Tensor, points: torch.Tensor, layout: Layout, level_weights: torch.Tensor,
           jacobian: bool = False):
    """Features (N, L * F) of `table` (rows, F) at points (N, 3) in [-1, 1]^3, each level scaled by
    its weight, and with `jacobian` their derivatives in the points (N, 3, L * F). Call only where
    `usable` says so."""
    level_weights = level_weights.to(torch.float32)
    feats, jac = _lookup_op(table, points, layout.res, layout.offsets, layout.hashed, layout.hash_mask,
                            level_weights, jacobian)
    return (feats, jac) if jacobian else feats
