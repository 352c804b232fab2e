"""What the property-based tests (Hypothesis) share: one fixed seed and a bounded number of
examples each, so that the default suite tries the same inputs on every run and stays fast, and
the check that a refusal is the tool's own (an InputError naming the file or field).

`VQM_FUZZ_EXAMPLES` raises the number of examples (benchmarks/stress.py runs thousands)."""

from __future__ import annotations

import os
from pathlib import Path

from hypothesis import HealthCheck, settings


def fuzz(examples: int) -> settings:
    """Hypothesis settings: `examples` examples (or $VQM_FUZZ_EXAMPLES), the same ones every run
    (derandomize: a seed from the test's own name), no deadline (a loaded machine is no failure),
    no example database written into the checkout."""
    return settings(max_examples=int(os.environ.get("VQM_FUZZ_EXAMPLES", examples)), derandomize=True,
                    database=None, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                         HealthCheck.too_slow])


# What Python itself says when a value of the wrong type reaches code that trusted it: an error
# message with one of these is a traceback in words, not the tool's sentence.
PYTHON_TEXT = ("invalid literal", "string indices", "object is not", "has no attribute", "unsupported operand",
               "not subscriptable", "not iterable", "could not convert", "NoneType", "positional argument",
               "unhashable", "index out of range", "out of bounds for axis", "bad_alloc", "MemoryError", "Traceback")


def python_text(message: str) -> str | None:
    """The first of PYTHON_TEXT in `message` (None when it has none)."""
    return next((t for t in PYTHON_TEXT if t in message), None)


def files_under(folder: Path) -> set[str]:
    """Every file and folder below `folder`, as relative paths."""
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}
