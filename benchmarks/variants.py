"""A benchmark's config variants on its command line: `default` (the shipped configuration) or
`NAME=KEY=VALUE[,KEY=VALUE...]`, its `--set` items. Imports nothing heavy (scripts that time a
step import torch only after vq_mitsuba has set its OpenMP defaults)."""

from __future__ import annotations


def parse_variant(text: str) -> tuple[str, list[str]]:
    """(name, its KEY=VALUE overrides) of a variant's text."""
    if text == "default":
        return "default", []
    name, sep, items = text.partition("=")
    if not sep or not items or "=" not in items:
        raise SystemExit(f"variant {text!r}: write NAME=KEY=VALUE[,KEY=VALUE...] or default")
    return name, items.split(",")


def labelled_runs(items: list[str]):
    """(label, run folder) of each `[LABEL=]RUN` on a command line (the label: the folder's name
    when none is given)."""
    from pathlib import Path

    out = []
    for item in items:
        label, sep, path = item.partition("=")
        run = Path(path if sep else item)
        out.append((label if sep else run.name, run))
    return out
