"""Equation numbers in the project match the paper's numbering.

The paper's LaTeX source (``../shared/paper/splat-slam.tex`` beside the checkout) is numbered
the way LaTeX would: every ``equation`` and every row of a non-starred ``align`` (or gather,
...) without ``\\nonumber``/``\\notag`` steps the counter, ``\\setcounter{equation}`` resets
it. The main body holds the equations up to ``\\appendix``; the supplementary material
continues after ``\\setcounter{equation}{15}``, so its equations are 16 and 17.

Checked:

* every equation reference in the tracked .py/.md/.yaml files ("Eq." / "Eqs." /
  "equation" followed by a number, a range "4-6" / "4–6" or a list "4-6, 10") names a
  main-body equation, or a supplementary one when it says "supp." / "supplementary", or
  says whose paper it is (e.g. "MonoGS Eq. 3", not checked); an "Eq." without a number
  is an error too;
* anchors: the paper's equation with a given label or distinctive token has the expected
  number, and the module implementing it names it with that number, so a renumbered paper
  or a stale reference fails.
"""
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import pytest

REPO = Path(__file__).resolve().parents[1]
PAPER = REPO.parent / "shared" / "paper" / "splat-slam.tex"
SUFFIXES = {".py", ".md", ".yaml", ".yml"}
THIS = Path(__file__).resolve()

LINE_ENVS = {"align", "gather", "flalign", "alignat", "eqnarray"}   # one number per row
SINGLE_ENVS = {"equation", "multline"}                             # one number in all
# works whose equations the project may cite, always by name ("MonoGS Eq. 3")
OTHER_WORKS = ("MonoGS", "DROID-SLAM", "DROID", "GlORIE-SLAM", "GlORIE", "GO-SLAM", "RAFT",
               "3DGS", "Photo-SLAM", "SplaTaM", "Gaussian-SLAM", "GS-SLAM", "Omnidata", "DPT")

REF = re.compile(r"(?:\bEqs?\.|\b[Ee]quations?)\s*\(?(\d+)((?:\s*[-–]\s*\d+)?"
                 r"(?:\s*,\s*\d+(?:\s*[-–]\s*\d+)?)*)")
BARE_EQ = re.compile(r"\bEqs?\.(?!\s*\(?\d)")
SUPP = re.compile(r"(?:\bsupp\.|\bsupplementary(?: material(?:'s)?)?)\s*$", re.I)
OTHER = re.compile(r"\b(?:" + "|".join(re.escape(w) for w in OTHER_WORKS)
                   + r")(?:'s)?(?: paper(?:'s)?)?,?\s*$")


@dataclass
class Equation:
    number: int
    label: Optional[str]
    body: str
    supplementary: bool


def _strip_comments(tex: str) -> str:
    return "\n".join(re.sub(r"(?<!\\)%.*", "", line) for line in tex.splitlines())


def _rows(body: str) -> List[str]:
    """Split an align-like body at its top-level ``\\\\`` (not inside braces or nested
    environments such as ``cases``)."""
    rows, depth, start = [], 0, 0
    for m in re.finditer(r"\\begin\{[^}]*\}|\\end\{[^}]*\}|\\\\|[{}]", body):
        t = m.group()
        if t.startswith("\\begin") or t == "{":
            depth += 1
        elif t.startswith("\\end") or t == "}":
            depth -= 1
        elif depth == 0:
            rows.append(body[start:m.start()])
            start = m.end()
    rows.append(body[start:])
    if len(rows) > 1 and not rows[-1].strip():      # a final "\\" opens no numbered row
        rows.pop()
    return rows


def number_equations(tex: str) -> List[Equation]:
    """The numbered equations of a LaTeX source, in order, as LaTeX numbers them."""
    tex = _strip_comments(tex)
    head = re.compile(r"\\setcounter\{equation\}\{(\d+)\}|\\appendix\b|\\begin\{("
                      + "|".join(sorted(LINE_ENVS | SINGLE_ENVS)) + r")\}")
    out: List[Equation] = []
    counter, supp, pos = 0, False, 0
    while True:
        m = head.search(tex, pos)
        if m is None:
            return out
        if m.group(1) is not None:
            counter, pos = int(m.group(1)), m.end()
            continue
        if m.group(2) is None:
            supp, pos = True, m.end()
            continue
        env = m.group(2)
        end = tex.index("\\end{%s}" % env, m.end())
        body, pos = tex[m.end():end], end
        for row in (_rows(body) if env in LINE_ENVS else [body]):
            if re.search(r"\\(?:nonumber|notag|tag)\b", row):
                continue
            counter += 1
            label = re.search(r"\\label\{([^}]*)\}", row)
            out.append(Equation(counter, label.group(1) if label else None, row, supp))


def references(line: str) -> List[Tuple[str, List[int]]]:
    """(kind, numbers) of every equation reference in a line; kind is "paper", "supp",
    "other" (another work's equation, named) or "bare" (an "Eq." without a number)."""
    out = []
    for m in REF.finditer(line):
        nums = [int(m.group(1))] + [int(x) for x in re.findall(r"\d+", m.group(2))]
        prefix = line[:m.start()]
        kind = "supp" if SUPP.search(prefix) else "other" if OTHER.search(prefix) else "paper"
        out.append((kind, nums))
    out += [("bare", []) for _ in BARE_EQ.finditer(line)]
    return out


def bad_references(line: str, n_main: int, supp_numbers: set) -> List[str]:
    """The references of ``line`` that name no equation of the paper."""
    bad = []
    for kind, nums in references(line):
        if kind == "bare":
            bad.append("an 'Eq.' without a number")
        elif kind == "paper" and not all(1 <= n <= n_main for n in nums):
            bad.append(f"Eq. {nums}: the paper's main body has Eq. 1-{n_main}")
        elif kind == "supp" and not all(n in supp_numbers for n in nums):
            bad.append(f"supp. Eq. {nums}: the supplementary has {sorted(supp_numbers)}")
    return bad


def tracked_files() -> List[Path]:
    try:
        names = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True,
                               check=True).stdout.splitlines()
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("git ls-files unavailable: not a git checkout")
    return [REPO / n for n in names
            if Path(n).suffix in SUFFIXES and (REPO / n).resolve() != THIS
            and (REPO / n).is_file()]


@pytest.fixture(scope="module")
def paper() -> List[Equation]:
    if not PAPER.is_file():
        pytest.skip(f"paper source not found at {PAPER} (only present in the dev/CI setup)")
    return number_equations(PAPER.read_text(encoding="utf-8"))


# ------------------------------------------------------------------ the checker itself
def test_numbering_rules_on_a_small_source():
    tex = r"""
\begin{equation} a \label{eq:a} \end{equation}
% \begin{equation} commented out \end{equation}
\begin{align} b \label{eq:b} \\ c \nonumber \\ d \begin{cases} x \\ y \end{cases} \\
\end{align}
\begin{equation*} unnumbered \end{equation*}
\appendix
\setcounter{equation}{15}
\begin{equation} e \label{eq:e} \end{equation}
"""
    eqs = number_equations(tex)
    assert [(e.number, e.label, e.supplementary) for e in eqs] == [
        (1, "eq:a", False), (2, "eq:b", False), (3, None, False), (16, "eq:e", True)]


def test_reference_checker_flags_wrong_numbers():
    def bad(s):
        return bad_references(s, 12, {16, 17})
    assert bad("the loss (Eq. 11), Eq. 4-6 and Eqs. 2–3, Eq. 4-6, 10") == []
    assert bad("IOU (supp. Eq. 16); MonoGS Eq. 33; equation 12") == []
    assert bad("Eq. 13") and bad("Eq. 4–13") and bad("Eq. 4-6, 14") and bad("Eq. 0")
    assert bad("supp. Eq. 15") and bad("Supp. Eq. 3") and bad("equation (13)")
    assert bad("the paper Eq. for alpha")
    assert bad("normal equations of Eq. 1") == []


# ------------------------------------------------------------------ the repository
def test_paper_numbering(paper):
    main = [e.number for e in paper if not e.supplementary]
    assert main == list(range(1, len(main) + 1)), main
    assert [e.number for e in paper if e.supplementary] == [16, 17]


def test_every_reference_names_a_paper_equation(paper):
    n_main = sum(not e.supplementary for e in paper)
    supp = {e.number for e in paper if e.supplementary}
    found = []
    for path in tracked_files():
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for why in bad_references(line, n_main, supp):
                found.append(f"{path.relative_to(REPO)}:{i}: {why}: {line.strip()}")
    assert found == [], "\n".join(found)


# (number, LaTeX label or None, distinctive token of the equation, implementing file,
#  phrase the file must contain, "{n}" standing for the number)
ANCHORS = [
    (1, "eq:dba", r"\mathop{\arg \min}_{\omega, d}", "splat_slam_ros/tracking/dense_ba.py",
     "(paper Eq. {n})"),
    (2, "eq:dba_wq", r"\mathop{\arg \min}_{d^{h}, \theta, \gamma}",
     "splat_slam_ros/tracking/dspo.py", "(paper §3.1, Eq. {n}-3)"),
    (3, "eq:wq_least_square", r"\{\theta_i,\,\gamma_i\}", "splat_slam_ros/depth/compose.py",
     "(Eq. {n}). Returns (theta, gamma)"),
    (4, None, r"[\hat{u},\hat{v}, 1]^T \propto", "splat_slam_ros/tracking/multiview.py",
     "Eq. {n}-5: p_i = T_i D_i(u,v)"),
    (5, "eq:back-project", r"p_{j} = \omega_j\tilde{D}_j", "splat_slam_ros/tracking/multiview.py",
     "Eq. 4-{n}: p_i = T_i D_i(u,v)"),
    (6, "eq:two_view_consist", r"\eta\cdot\text{average}(\tilde{D}_i)",
     "splat_slam_ros/tracking/multiview.py", "n_i(u, v) of Eq. {n}"),
    (6, "eq:two_view_consist", r"n_{i}(u,v)", "splat_slam_ros/config.py", "eta in Eq. {n}"),
    (8, None, r"D^r = \sum_{i \in \mathcal{N}}", "splat_slam_ros/mapping/rasterizer/reference.py",
     "(paper Eq. {n})"),
    (9, None, r"\alpha_i = o_i \exp", "splat_slam_ros/mapping/rasterizer/reference.py",
     "(paper Eq. {n})"),
    (10, None, r"\theta D^{\text{mono}}(u,v)+\gamma", "splat_slam_ros/depth/proxy_depth.py",
     '"Map Initialization", Eq. {n})'),
    (11, "eq:pix_warp_loss", r"\frac{\lambda_{reg}}{|\mathcal{G}|}",
     "splat_slam_ros/mapping/optimise.py", "Eq. {n} loss summed over the window"),
    (11, "eq:pix_warp_loss", r"(a_kC_k+b_k)", "splat_slam_ros/config.py", "lambda_reg in Eq. {n}"),
    (12, None, r"R_i' = R'R^{-1}R_i", "splat_slam_ros/mapping/deformation.py",
     "Eq. {n} of the paper"),
    (16, "eq:iou_cov", r"\text{IOU}_{\text{cov}}", "splat_slam_ros/mapping/keyframe_window.py",
     "(supp. Eq. {n})"),
    (17, "eq:oc_cov", r"\text{OC}_{\text{cov}}", "splat_slam_ros/mapping/keyframe_window.py",
     "(supp. Eq. {n})"),
]


def _squash(s: str) -> str:
    return re.sub(r"\s+", "", s)


@pytest.mark.parametrize("number,label,token,path,phrase", ANCHORS,
                         ids=[f"eq{a[0]}-{Path(a[3]).stem}" for a in ANCHORS])
def test_anchor(paper, number, label, token, path, phrase):
    with_token = [e for e in paper if _squash(token) in _squash(e.body)]
    assert [e.number for e in with_token] == [number], \
        f"the equation with {token!r} is numbered {[e.number for e in with_token]}, not {number}"
    if label is not None:
        assert with_token[0].label == label
    text = (REPO / path).read_text(encoding="utf-8")
    assert phrase.format(n=number) in text, f"{path} does not say {phrase.format(n=number)!r}"
