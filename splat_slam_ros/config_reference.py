"""The configuration reference (docs/configuration.md), generated from the schema.

The keys, types and defaults come from the dataclasses in :mod:`splat_slam_ros.config`;
the descriptions from the comments beside and above each field in its source; the preset
table from the files in ``config/``. Regenerate after changing any of them::

    python -m splat_slam_ros.config_reference            # writes docs/configuration.md
    python -m splat_slam_ros.config_reference --check    # exit 1 when the file is stale
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import io
import json
import re
import sys
import tokenize
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from splat_slam_ros import config as config_module
from splat_slam_ros.config import ADVANCED, SlamConfig, config_dir, is_core, load_config

DEFAULT_OUT = Path(__file__).resolve().parent.parent / "docs" / "configuration.md"
REGENERATE = "python -m splat_slam_ros.config_reference"

HEADER = f"""# Configuration reference

<!-- Generated from splat_slam_ros/config.py and config/ by `{REGENERATE}`.
Do not edit by hand: change config.py (its comments are the descriptions) or a preset
file, then regenerate; tests/test_config_reference.py fails while this file is stale. -->

Every stage, in the offline pipeline and in the ROS 2 nodes, reads one schema
(`SlamConfig` in `splat_slam_ros/config.py`). A key is named `section.key`, e.g.
`tracking.keyframe_thresh`, the same everywhere. Values apply in this order, later ones
winning:

1. the defaults listed below;
2. `--preset NAME`: the shipped file `config/NAME.yaml` (see [Presets](#presets)),
   e.g. `splat-slam-run DATA --out runs/paper --preset paper`;
3. `--config FILE.yaml`: a YAML file nesting keys under their section, e.g.
   `tracking: {{keyframe_thresh: 3.0}}`, the advanced keys under a top-level `{ADVANCED}:`
   section nested the same way, e.g. `{ADVANCED}: {{tracking: {{loop_nms: 10}}}}` (an
   advanced key is also read at its section; a core key under `{ADVANCED}:` is an error);
   unknown keys and wrong types are errors;
4. `--set KEY=VALUE`, repeatable, the value read as YAML, e.g.
   `--set tracking.keyframe_thresh=3.0 --set mapping.raster_backend=torch`.

`splat-slam-run` and `splat-slam-launch` take all four. A single node takes the file and
the keys as ROS parameters: `splat-slam-tracker-node --ros-args -p config_file:=my.yaml
-p tracking.keyframe_thresh:=3.0`.

The [core keys](#core-keys) are what a user sets for a camera, a machine or the outputs.
Every other key is advanced: a method constant, a CPU budget or an ablation switch whose
default was measured; its effect is described below and in the stage's page in docs/. A
preset changes advanced keys for a data set or a schedule (see [Presets](#presets)).
Every run writes the whole configuration it used to `OUT/config.yaml` in this layout.

This file is generated; to regenerate it: `{REGENERATE}`
(`--check` only tests that it is up to date).
"""


# ------------------------------------------------------------------ comments -> fields
def _comment_lines(source: str) -> Tuple[Dict[int, Tuple[int, str]], set]:
    """({line: (column, text)} of every comment, the set of lines holding code)."""
    comments, code = {}, set()
    skip = (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT,
            tokenize.DEDENT, tokenize.ENDMARKER, tokenize.ENCODING)
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0]] = (tok.start[1], tok.string.lstrip("#").strip())
        elif tok.type not in skip:
            code.update(range(tok.start[0], tok.end[0] + 1))
    return comments, code


def _join(lines: List[str]) -> str:
    """Comment lines -> one paragraph (a word hyphenated at a line end is rejoined)."""
    out = ""
    for s in (s for s in lines if s):
        glue = "" if not out or (out.endswith("-") and out[-2:-1].isalpha()) else " "
        out += glue + s
    return out


def _sentences(*parts: str) -> str:
    """Join text parts: "; " after one not ending in punctuation, else a space (and the
    next part's first word capitalised when it is a plain lowercase word)."""
    out = ""
    for part in (p for p in parts if p):
        if out and out[-1] in ".!?:;":
            word = part.split(" ", 1)[0]
            part = part[0].upper() + part[1:] if word.isalpha() and word.islower() else part
            out += " " + part
        else:
            out += ("; " if out else "") + part
    return out


def field_docs(source: str) -> Dict[str, Tuple[str, Dict[str, str]]]:
    """{class name: (class description, {field name: description})} of every class in
    ``source``. A field's description is the comment lines directly above it (at its
    indentation) followed by its trailing comment and the comment lines aligned under
    that one. A class's description is its docstring, else a comment block opening its
    body that a blank line separates from the first field."""
    comments, code = _comment_lines(source)
    alone = {n: c for n, c in comments.items() if n not in code}
    out = {}
    for cls in (n for n in ast.walk(ast.parse(source)) if isinstance(n, ast.ClassDef)):
        docs: Dict[str, str] = {}
        for st in cls.body:
            if not (isinstance(st, ast.AnnAssign) and isinstance(st.target, ast.Name)):
                continue
            above, n = [], st.lineno - 1
            while n in alone and alone[n][0] == st.col_offset:
                above.insert(0, alone[n][1])
                n -= 1
            lines = [n for n in range(st.lineno, st.end_lineno + 1)
                     if n in comments and n not in alone]
            trailing = [comments[n][1] for n in lines]
            n = st.end_lineno + 1
            while lines and n in alone and alone[n][0] == comments[lines[-1]][0]:
                trailing.append(alone[n][1])
                n += 1
            docs[st.target.id] = _sentences(_join(above), _join(trailing))
        doc = ast.get_docstring(cls) or ""
        if not doc and cls.body:
            lead, n = [], cls.lineno + 1
            while n in alone:
                lead.append(alone[n][1])
                n += 1
            doc = _join(lead) if lead and n < cls.body[0].lineno else ""
        out[cls.name] = ("\n\n".join(" ".join(par.split()) for par in doc.split("\n\n")),
                         docs)
    return out


# ------------------------------------------------------------------ schema -> rows
def _default(f: dataclasses.Field):
    return f.default_factory() if f.default is dataclasses.MISSING else f.default


def format_value(v) -> str:
    """A value as a user writes it in YAML / ``--set``."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(format_value(x) for x in v) + "]"
    text = repr(v)
    if isinstance(v, float) and "e" in text and "." not in text:
        text = text.replace("e", ".0e")        # 1e-05 would read back as a YAML string
    return text


def rows() -> List[Tuple[str, str, List[dict]]]:
    """[(section, its description, [{key, type, default, description, choices}])] in
    SlamConfig order; section "" holds the top-level keys."""
    docs = field_docs(inspect.getsource(config_module))
    out = []
    sections = [("", SlamConfig)] + [(f.name, type(_default(f))) for f in dataclasses.fields(
        SlamConfig) if dataclasses.is_dataclass(_default(f))]
    for name, cls in sections:
        text, comments = docs.get(cls.__name__, ("", {}))
        items = []
        for f in dataclasses.fields(cls):
            v = _default(f)
            if dataclasses.is_dataclass(v):
                continue
            typ = "list" if isinstance(v, tuple) else getattr(f.type, "__name__", f.type)
            key = f"{name}.{f.name}" if name else f.name
            items.append({"key": key, "type": typ, "core": is_core(key),
                          "default": format_value(v), "description": comments.get(f.name, ""),
                          "choices": list(f.metadata.get("choices", ()))})
        out.append((name, text, items))
    return out


def first_sentence(text: str) -> str:
    """The first sentence of the comment block opening a YAML file ("" if none)."""
    lead = []
    for ln in text.splitlines():
        if not ln.startswith("#"):
            break
        lead.append(ln.lstrip("#").strip())
    return re.split(r"(?<=[.!?])\s+(?=[A-Z0-9])", _join(lead), maxsplit=1)[0]


def presets() -> List[Tuple[str, str, List[str]]]:
    """[(file name, its description, ["key: value" it changes vs the defaults])]."""
    base = SlamConfig().flat()
    out = []
    for p in sorted(config_dir().glob("*.yaml")):
        first = first_sentence(p.read_text())
        flat = load_config(p).flat()
        changed = [f"{k}: {format_value(v)}" for k, v in flat.items() if v != base[k]]
        out.append((p.name, first, changed))
    return out


# ------------------------------------------------------------------ Markdown
def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _row(r: dict) -> str:
    desc = r["description"]
    if r["choices"]:
        desc = _sentences(desc + ("." if desc and desc[-1] not in ".!?" else ""),
                          "Choices: " + ", ".join(f"`{c}`" for c in r["choices"]))
    return f"| `{r['key']}` | {r['type']} | `{r['default']}` | {_cell(desc)} |"


def render() -> str:
    """The whole reference as Markdown: the core keys in one table, then each section's
    advanced keys."""
    lines = [HEADER]
    table = ["| key | type | default | description |", "|---|---|---|---|"]
    sections = rows()
    lines += ["## Core keys", "", "Written under their section in a YAML file.", ""] + table
    lines += [_row(r) for _, _, items in sections for r in items if r["core"]] + [""]
    for name, text, items in sections:
        advanced = [r for r in items if not r["core"]]
        if not advanced:
            continue
        lines += [f"## {name} (advanced)", ""]
        if text:
            lines += [text, ""]
        lines += [f"Written under `{ADVANCED}: {{{name}: ...}}` in a YAML file.", ""] + table
        lines += [_row(r) for r in advanced] + [""]
    lines += ["## Presets", "",
              "The files in `config/`: pass one as `--preset NAME` (without `.yaml`) or "
              "`--config config/NAME.yaml`. The last column lists the keys each changes "
              "from the defaults above.", "",
              "| preset | description | changes |", "|---|---|---|"]
    for fname, first, changed in presets():
        ch = "<br>".join(f"`{c}`" for c in changed) or "(none)"
        lines.append(f"| `{Path(fname).stem}` | {_cell(first)} | {_cell(ch)} |")
    return "\n".join(lines) + "\n"


def main(argv: Optional[List[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m splat_slam_ros.config_reference",
                                 description="Write (or --check) the configuration reference.")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT,
                    help="Markdown file (default: docs/configuration.md of the checkout)")
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 if --out differs from the schema")
    a = ap.parse_args(argv)
    text = render()
    if a.check:
        if not a.out.is_file() or a.out.read_text() != text:
            print(f"{a.out} is stale: regenerate it with `{REGENERATE}`", file=sys.stderr)
            return 1
        print(f"{a.out} is up to date")
        return 0
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
