"""The documentation stays a manual, and its references stay true.

* README.md is at most ``README_MAX_LINES`` lines: a user manual; the technical detail lives in
  docs/, the history in CHANGELOG.md.
* No development-history references ("session" followed by a number, any case) and no
  absolute machine paths (``/work/``, ``/tmp/``, ``/home/``, ``/root/``, ``C:\\``) in any file
  of the checkout (docs, code, config, benchmarks, tests), this file excepted (it names the
  patterns). Tests build temporary paths from ``tmp_path`` / ``tempfile``, never literally.
* Every relative Markdown link in the Markdown files points to an existing file, and a
  ``#anchor`` to an existing heading of that file (GitHub's slug rules). Links that leave the
  repository (``../shared/...``, present only beside a full checkout) are not checked.
* Every ``README "Heading"`` / ``docs/x.md "Heading"`` reference (double or single quotes) in
  any file names an existing file and one of its headings, verbatim (backticks aside).

"The checkout" is what git tracks plus untracked files it does not ignore, minus deleted files.
"""
import re
import subprocess
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple

REPO = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()
README_MAX_LINES = 300

HISTORY = re.compile(r"\bsessions?[ \t_-]*\d+", re.IGNORECASE)
MACHINE_PATH = re.compile(r"(?<![\w.~/-])/(?:work|tmp|home|root)/|(?<![\w])[A-Z]:\\")
FENCE = re.compile(r"^\s*(```|~~~)")
ATX = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
INLINE_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]*)>?(?:\s+[\"'][^)]*[\"'])?\s*\)")
REF_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")
HEADING_REF = re.compile(r"(?<![\w/.-])(README(?:\.md)?|(?:[\w.-]+/)*[\w.-]+\.md)[ \t]+"
                         r"(?:\"([^\"\n]+)\"|'([^'\n]+)')")


def checkout_files() -> List[str]:
    out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         cwd=REPO, capture_output=True, check=True).stdout.decode()
    return sorted(p for p in set(out.split("\0")) if p and (REPO / p).is_file())


def text_files() -> Iterator[Tuple[str, str]]:
    """(repo-relative path, text) of every UTF-8 file of the checkout but this one."""
    for rel in checkout_files():
        path = REPO / rel
        if path.resolve() == THIS:
            continue
        try:
            yield rel, path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue                       # images and other binary files


def markdown_files() -> List[str]:
    return [p for p in checkout_files() if p.endswith(".md")]


# --------------------------------------------------------------------------- Markdown
def prose_lines(text: str) -> Iterator[Tuple[int, str]]:
    """(line number, line) outside fenced code blocks."""
    fenced = None
    for no, line in enumerate(text.splitlines(), 1):
        m = FENCE.match(line)
        if m:
            if fenced is None:
                fenced = m.group(1)
            elif m.group(1) == fenced:
                fenced = None
            continue
        if fenced is None:
            yield no, line


def heading_text(raw: str) -> str:
    """A heading as rendered: links by their text, emphasis and code marks dropped."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", raw)
    text = text.replace("`", "").replace("**", "").replace("*", "")
    return " ".join(text.split())


def headings(text: str) -> List[str]:
    return [heading_text(m.group(2)) for _, line in prose_lines(text)
            for m in [ATX.match(line)] if m]


def slug(heading: str) -> str:
    """GitHub's anchor: lower case, punctuation dropped (letters, digits, ``_``, ``-`` and
    spaces stay), each space a hyphen."""
    return re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")


def anchors(text: str) -> set:
    seen: Dict[str, int] = {}
    out = set()
    for h in headings(text):
        s = slug(h)
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return out


def links(text: str) -> Iterator[Tuple[int, str]]:
    for no, line in prose_lines(text):
        line = CODE_SPAN.sub("", line)
        for m in INLINE_LINK.finditer(line):
            yield no, m.group(1)
        m = REF_LINK.match(line)
        if m:
            yield no, m.group(1)


def link_problem(md_file: Path, target: str) -> Optional[str]:
    """Why a link target in ``md_file`` is broken, or None (fine or not checkable)."""
    if not target or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
        return None                        # URL, mailto: ...
    path_part, _, frag = target.partition("#")
    dest = (md_file.parent / path_part).resolve() if path_part else md_file.resolve()
    try:
        dest.relative_to(REPO)
    except ValueError:
        return None                        # outside the repository (../shared/...)
    if not dest.exists():
        return f"{path_part}: no such file"
    if frag and dest.suffix == ".md" and frag not in anchors(dest.read_text(encoding="utf-8")):
        return f"#{frag}: no such heading in {dest.relative_to(REPO)}"
    return None


def broken_links(md_file: Path) -> List[str]:
    out = []
    for no, target in links(md_file.read_text(encoding="utf-8")):
        why = link_problem(md_file, target)
        if why:
            out.append(f"{md_file.relative_to(REPO)}:{no}: ({target}) {why}")
    return out


# --------------------------------------------------------------------------- references
def heading_refs(text: str) -> Iterator[Tuple[int, str, str]]:
    """(line, file, heading) of every ``README "Heading"`` / ``docs/x.md 'Heading'``."""
    for no, line in enumerate(text.splitlines(), 1):
        for m in HEADING_REF.finditer(line):
            name = m.group(1)
            yield no, "README.md" if name == "README" else name, m.group(2) or m.group(3)


def ref_problem(name: str, heading: str) -> Optional[str]:
    path = REPO / name
    if not path.is_file():
        return f"{name}: no such file"
    if heading_text(heading) not in headings(path.read_text(encoding="utf-8")):
        return f"{name} has no heading \"{heading}\""
    return None


def pattern_hits(pattern: re.Pattern) -> List[str]:
    return [f"{rel}:{no}: {line.strip()[:120]}"
            for rel, text in text_files()
            for no, line in enumerate(text.splitlines(), 1) if pattern.search(line)]


# --------------------------------------------------------------------------- the checkout
def test_readme_is_a_manual_of_at_most_300_lines():
    n = len((REPO / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, (
        f"README.md has {n} lines (at most {README_MAX_LINES}): move the detail to a page in "
        "docs/ and history to CHANGELOG.md")


def test_no_development_history_references():
    hits = pattern_hits(HISTORY)
    assert not hits, ("say the version or the date, not the development session:\n"
                      + "\n".join(hits))


def test_no_absolute_machine_paths():
    hits = pattern_hits(MACHINE_PATH)
    assert not hits, "absolute machine paths (use relative paths or tmp_path):\n" + "\n".join(hits)


def test_markdown_links_point_to_existing_files_and_headings():
    files = markdown_files()
    assert "README.md" in files and any(f.startswith("docs/") for f in files)
    broken = [b for f in files for b in broken_links(REPO / f)]
    assert not broken, "broken Markdown links:\n" + "\n".join(broken)


def test_heading_references_name_existing_headings():
    refs, bad = 0, []
    for rel, text in text_files():
        for no, name, heading in heading_refs(text):
            refs += 1
            why = ref_problem(name, heading)
            if why:
                bad.append(f"{rel}:{no}: {why}")
    assert refs >= 10, f"only {refs} heading references found: is the pattern still right?"
    assert not bad, "references to missing headings:\n" + "\n".join(bad)


# --------------------------------------------------------------------------- the checkers
def test_checkers_catch_what_they_are_for(tmp_path):
    assert HISTORY.search("measured in Session 14") and HISTORY.search("session-11 machine")
    assert not HISTORY.search('@pytest.fixture(scope="session")')
    assert MACHINE_PATH.search("see /work/main/x") and MACHINE_PATH.search(r"C:\Users\me")
    assert not MACHINE_PATH.search("runs/x_report, ~/.cache/x, /var/tmp/x, print('error:\\n')")
    assert slug("Soak: 10 000 frames in one room") == "soak-10-000-frames-in-one-room"
    assert slug(heading_text("Live camera: `bench_live.py`, on demand")) == \
        "live-camera-bench_livepy-on-demand"
    assert anchors("# A\n## A\n```\n# not a heading\n```\n") == {"a", "a-1"}

    (tmp_path / "other.md").write_text("# Title\n\n## Some section\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#some-section) [gone](missing.md) [bad](other.md#nope)\n"
                    "`[code](missing.md)` [web](https://example.org/x.md) [self](#top)\n"
                    "```\n[fenced](missing.md)\n```\n# Top\n")
    found = [t for _, t in links(page.read_text())]
    assert found == ["other.md#some-section", "missing.md", "other.md#nope",
                     "https://example.org/x.md", "#top"]
    orig = globals()["REPO"]
    globals()["REPO"] = tmp_path          # link_problem checks the target is inside REPO
    try:
        problems = [link_problem(page, t) for t in found]
    finally:
        globals()["REPO"] = orig
    assert problems[0] is None and problems[3] is None and problems[4] is None
    assert "no such file" in problems[1] and "no such heading" in problems[2]

    refs = list(heading_refs("x  # see README \"Tracking\"; docs/mapping.md 'Budgets' and\n"
                             "(DOCS / \"README.md\").read_text()\n"))
    assert refs == [(1, "README.md", "Tracking"), (1, "docs/mapping.md", "Budgets")]
    assert ref_problem("docs/mapping.md", "No such heading anywhere") is not None
    assert ref_problem("docs/no_such_page.md", "X") is not None
