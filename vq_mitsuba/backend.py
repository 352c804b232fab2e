"""The Mitsuba variant and the torch device, chosen once for the whole process."""

from __future__ import annotations

import os

import mitsuba as mi
import torch

_VARIANT_READY = False


def init_mitsuba(variant: str | None = None) -> str:
    """Select the Mitsuba variant once: `cuda_ad_rgb` when a GPU works, else `llvm_ad_rgb`."""
    global _VARIANT_READY
    if not _VARIANT_READY:
        if variant is None:
            variant = "llvm_ad_rgb"
            if torch.cuda.is_available():
                try:
                    mi.set_variant("cuda_ad_rgb")
                    variant = "cuda_ad_rgb"
                except Exception:  # no usable CUDA driver for Dr.Jit
                    variant = "llvm_ad_rgb"
        if mi.variant() != variant:
            mi.set_variant(variant)
        _VARIANT_READY = True
    return mi.variant()


def torch_device() -> torch.device:
    """The torch device matching the Mitsuba variant (tensors cross `dr.wrap` without copies)."""
    return torch.device("cuda") if mi.variant().startswith("cuda") else torch.device("cpu")


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask, e.g. under taskset or a container quota)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def max_threads() -> int:
    """The most threads `set_threads` takes: 4 per core of the machine (more only add switching,
    and thousands of them exhaust the stacks Dr.Jit's pool allocates)."""
    return 4 * max(1, os.cpu_count() or 1)


def set_threads(n: int | None = None) -> int:
    """Use n CPU threads (default: the available cores) in torch and in Dr.Jit's LLVM backend.

    OpenMP's worker threads wait passively (OMP_WAIT_POLICY=PASSIVE, set when vq_mitsuba is
    imported first): spinning threads would fight a busy neighbour process for the same cores."""
    import drjit as dr

    from vq_mitsuba.errors import InputError

    most = max_threads()
    if n is not None and not 0 <= int(n) <= most:
        raise InputError(None, f"--threads {n}: expected 1 to {most} (4 per core of the {os.cpu_count() or 1} "
                               "this machine has)")
    n = available_cores() if not n else int(n)
    torch.set_num_threads(n)
    # Mitsuba reads EXR files with nested tasks on Dr.Jit's pool, which wait forever on a pool of
    # one worker: Dr.Jit gets two threads at least (the second sleeps while the first computes).
    dr.set_thread_count(max(n, 2))
    return n
