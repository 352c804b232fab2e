"""The prose docs against the code: every command line they show uses options its command has,
every `section.key` they name is a config key, and every default their key tables give is the
config's. (docs/cli.md and docs/configuration.md are generated; tests/cli/test_cli.py holds them.)"""

import argparse
import re
from pathlib import Path

import pytest

from vq_mitsuba.cli import build_parser
from vq_mitsuba.config import load_config, to_dict

ROOT = Path(__file__).resolve().parents[2]
PROSE = [ROOT / "README.md"] + [p for p in sorted((ROOT / "docs").glob("*.md"))
                                if p.name not in ("cli.md", "configuration.md")]
FILE_SUFFIXES = (".pt", ".json", ".exr", ".png", ".hdr", ".py", ".ply", ".yaml", ".jpg")
NOT_KEYS = {"vq.light_from_continuous": "a key of older benchmark records, named as such",
            "envmap.checks": "a key of fit.json's decisions"}
DEFAULTS = to_dict(load_config(None))


def _options() -> dict[str, set[str]]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {name: {o for a in p._actions for o in a.option_strings} for name, p in sub.choices.items()}


def _synopses(text: str):
    """(first line, the command line with its continuation lines) of each `vq-mitsuba CMD` shown."""
    lines, fenced = text.splitlines(), False
    for i, line in enumerate(lines):
        fenced ^= line.startswith("```")
        m = re.search(r"(?:^|`)vq-mitsuba ([a-z][a-z-]*)" if fenced else r"`vq-mitsuba ([a-z][a-z-]*)", line)
        if not m:
            continue
        parts = [line[m.start():]]
        if fenced and line.startswith("vq-mitsuba"):  # a block's synopsis: indented lines continue it
            for nxt in lines[i + 1:]:
                if not nxt.startswith(" ") or "vq-mitsuba" in nxt:
                    break
                parts.append(nxt)
        else:
            parts = [line[m.start() + 1:].split("`")[0]]
        yield i + 1, m.group(1), " ".join(parts).split("#")[0]


@pytest.mark.parametrize("doc", PROSE, ids=lambda p: p.name)
def test_command_lines_in_the_docs_use_real_options(doc):
    options = _options()
    wrong = []
    for line, command, text in _synopses(doc.read_text()):
        if command not in options:
            wrong.append(f"{doc.name}:{line}: no command '{command}'")
            continue
        for opt in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", text):
            if opt not in options[command]:
                wrong.append(f"{doc.name}:{line}: `vq-mitsuba {command}` has no {opt}")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("doc", PROSE, ids=lambda p: p.name)
def test_keys_named_in_the_docs_exist(doc):
    pattern = r"`((%s)\.([a-z_0-9]+))(?![a-z_0-9.])" % "|".join(DEFAULTS)
    wrong = [m.group(1) for m in re.finditer(pattern, doc.read_text())
             if not m.group(1).endswith(FILE_SUFFIXES) and m.group(3) not in DEFAULTS[m.group(2)]
             and m.group(1) not in NOT_KEYS]
    assert not wrong, f"{doc.name} names config keys that do not exist: {wrong}"


def _same(shown: str, default) -> bool:
    shown = re.sub(r"\(.*?\)", "", shown).strip().rstrip("°").strip()
    if shown == "auto":
        return default in (0, "auto", "")
    if isinstance(default, bool):
        return shown == str(default).lower()
    if isinstance(default, (int, float)):
        try:
            return float(shown) == float(default)
        except ValueError:
            return False
    return shown.strip("`") == str(default)


def _split_top(cell: str) -> list[str]:
    """A cell split at the commas outside parentheses."""
    items, depth, cur = [], 0, ""
    for ch in cell:
        depth += (ch == "(") - (ch == ")")
        if ch == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += ch
    return items + [cur]


@pytest.mark.parametrize("doc", PROSE, ids=lambda p: p.name)
def test_defaults_in_the_docs_key_tables_are_the_configs(doc):
    wrong, checked = [], 0
    for line in doc.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("| `") or len(cells) < 3:
            continue
        keys = re.findall(r"`([a-z]+)\.([a-z_0-9]+)`", cells[0])
        shown = _split_top(cells[1])
        if not keys or any(s not in DEFAULTS for s, _ in keys) or len(shown) != len(keys):
            continue
        section = keys[0][0]
        for (sec, key), value in zip(keys, shown):
            key = key if key in DEFAULTS[sec] else None
            if key is None:
                continue
            checked += 1
            if not _same(value, DEFAULTS[sec][key]):
                wrong.append(f"{sec}.{key}: the doc says {value.strip()}, the config {DEFAULTS[sec][key]!r}")
    assert not wrong, f"{doc.name}: " + "; ".join(wrong)
    if doc.name == "geometry.md":  # its table of NeuS keys is read, not skipped
        assert checked >= 20, checked
