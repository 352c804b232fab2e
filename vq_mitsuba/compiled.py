"""Hot loops compiled with `torch.compile`, the eager function kept as the fallback.

Inductor fuses a step's chains of small elementwise passes into one loop (C++ and OpenMP on a CPU,
Triton on a GPU). A function is compiled on its first call; its compiled code is cached on disk
in the user's cache folder (`$XDG_CACHE_HOME/vq-mitsuba/torch`, never in a run), so the next
process with the same shapes loads it in about a second instead of compiling it again. Where
compilation or a compiled call fails (no C compiler, an unsupported operation, a platform without
Inductor), the function runs eagerly from then on, after one warning: the same arithmetic, slower.
`TORCH_COMPILE_DISABLE=1` (torch's own switch) runs everything eagerly.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Callable

from vq_mitsuba.errors import warn


def cache_dir() -> Path:
    """Where compiled code is kept: the user's cache folder, shared by runs."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "vq-mitsuba" / "torch"


def _use_cache_dir() -> None:
    # Inductor reads its folder from the environment when it compiles; a folder the user set wins.
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(cache_dir() / "inductor"))
    os.environ.setdefault("TRITON_CACHE_DIR", str(cache_dir() / "triton"))


class Compiled:
    """`fn` compiled by torch.compile on its first call (static shapes: a new shape compiles
    again), or `fn` itself once compiling or a compiled call has failed (warned once).
    `state`: 'pending' before the first call, then 'compiled' or 'eager'."""

    def __init__(self, fn: Callable, name: str, data_dependent_shapes: bool = False):
        self.fn, self.name = fn, name
        # with data_dependent_shapes, an operation whose output's size depends on values
        # (`nonzero`) stays inside the graph, its size symbolic, instead of breaking it in two
        self.data_dependent_shapes = data_dependent_shapes
        self.state, self.reason = "pending", ""
        self._compiled: Callable | None = None

    def __call__(self, *args, **kwargs):
        if self.state == "eager":
            return self.fn(*args, **kwargs)
        try:
            if self._compiled is None:
                import torch

                _use_cache_dir()
                self._compiled = torch.compile(self.fn, dynamic=False)
            import torch._dynamo

            with (torch._dynamo.config.patch(capture_dynamic_output_shape_ops=True) if self.data_dependent_shapes
                  else contextlib.nullcontext()):
                out = self._compiled(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - any compiler failure: the eager function is the answer
            self.fallback(exc)
            return self.fn(*args, **kwargs)
        self.state = "compiled"
        return out

    def fallback(self, exc: BaseException) -> None:
        """Run eagerly from now on, saying why once."""
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        self.state, self.reason = "eager", f"{type(exc).__name__}: {first}"
        warn(f"{self.name}: torch.compile failed ({self.reason}); it runs eagerly")
