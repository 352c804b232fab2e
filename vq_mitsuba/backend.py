"""The Mitsuba variant and the torch device, chosen once for the whole process."""

from __future__ import annotations

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
