"""Code-shape rules of the library, the scene generator and the nodes: no module over 600
lines, no class over 400, no function over 120; no import circles (module-level and
function-level imports); the stage packages layered as the paper runs (``io`` < ``tracking``
< ``depth`` < ``mapping``: a stage imports only lower ones, ``io`` none of them, and none
imports the run-level modules above them); no dynamic imports except the loader of the
JIT-built C++ kernels (``native``: a .so by path)."""
import ast
from pathlib import Path
from typing import Dict, List, Set, Tuple

REPO = Path(__file__).resolve().parents[1]
ROOTS = {"splat_slam_ros": REPO / "splat_slam_ros", "splat_slam_nodes": REPO / "nodes",
         "splat_slam_synth": REPO / "splat_slam_synth"}
MAX_FILE_LINES = 600
MAX_CLASS_LINES = 400
MAX_FUNCTION_LINES = 120
# the stage packages, lowest first: each may import the ones before it, never a later one
STAGES = ("io", "tracking", "depth", "mapping")
# shared low-level modules of the library every stage may use
BASE = {"geometry", "types", "config", "heap", "runtime", "extras", "imaging", "native"}
DYNAMIC_IMPORT_ALLOWED = {"splat_slam_ros.native"}


def modules() -> Dict[str, Tuple[Path, bool]]:
    """{dotted module name: (file, is a package __init__)} of both packages."""
    out = {}
    for pkg, root in ROOTS.items():
        for p in sorted(root.rglob("*.py")):
            parts = [pkg, *p.relative_to(root).with_suffix("").parts]
            is_pkg = parts[-1] == "__init__"
            out[".".join(parts[:-1] if is_pkg else parts)] = (p, is_pkg)
    return out


def import_graph(mods) -> Dict[str, Set[str]]:
    """Edges module -> project module it imports (anywhere in the file)."""
    def known(name):
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph = {m: set() for m in mods}
    for m, (path, is_pkg) in mods.items():
        base = m if is_pkg else m.rpartition(".")[0]
        for n in ast.walk(ast.parse(path.read_text())):
            targets: List[str] = []
            if isinstance(n, ast.Import):
                targets = [a.name for a in n.names]
            elif isinstance(n, ast.ImportFrom):
                mod = n.module or ""
                if n.level:
                    b = base
                    for _ in range(n.level - 1):
                        b = b.rpartition(".")[0]
                    mod = f"{b}.{mod}" if mod else b
                targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in mods else mod
                           for a in n.names]
            for t in targets:
                k = known(t)
                if k and k != m:
                    graph[m].add(k)
    return graph


def cycles(graph) -> List[List[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_circle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circles():
    assert cycles(import_graph(modules())) == []


def test_file_class_and_function_sizes():
    long_files, long_classes, long_funcs = [], [], []
    for m, (path, _) in modules().items():
        text = path.read_text()
        if text.count("\n") > MAX_FILE_LINES:
            long_files.append((m, text.count("\n")))
        for n in ast.walk(ast.parse(text)):
            size = getattr(n, "end_lineno", 0) - getattr(n, "lineno", 0) + 1
            if isinstance(n, ast.ClassDef) and size > MAX_CLASS_LINES:
                long_classes.append((m, n.name, size))
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if size > MAX_FUNCTION_LINES:
                    long_funcs.append((m, n.name, size))
    assert long_files == [] and long_classes == [] and long_funcs == []


def stage_violations(graph) -> List[Tuple[str, str]]:
    """(importer, imported) pairs that break the stage layering: a stage package importing a
    later stage, or anything of the library outside the stages and BASE (the run-level
    modules: roles, pipeline, evaluation, report, cli ...); a BASE module importing anything
    but BASE."""
    def place(m):
        parts = m.split(".")
        if parts[0] != "splat_slam_ros" or len(parts) < 2:
            return None
        return parts[1]

    bad = []
    for m, deps in graph.items():
        own = place(m)
        if own not in STAGES and own not in BASE:
            continue
        for d in deps:
            other = place(d)
            if other is None or other == own or other in BASE:
                continue
            if own in BASE or other not in STAGES or STAGES.index(other) > STAGES.index(own):
                bad.append((m, d))
    return sorted(bad)


def test_stage_rule_finds_upward_imports():
    g = {"splat_slam_ros.io.a": {"splat_slam_ros.mapping.m", "splat_slam_ros.geometry"},
         "splat_slam_ros.tracking.t": {"splat_slam_ros.io.a", "splat_slam_ros.depth.d"},
         "splat_slam_ros.depth.d": {"splat_slam_ros.tracking.t", "splat_slam_ros.roles"},
         "splat_slam_ros.mapping.m": {"splat_slam_ros.depth.d", "splat_slam_ros.io.a"},
         "splat_slam_ros.roles": {"splat_slam_ros.mapping.m"},
         "splat_slam_ros.geometry": {"splat_slam_ros.types", "splat_slam_ros.io.a"}}
    assert stage_violations(g) == [("splat_slam_ros.depth.d", "splat_slam_ros.roles"),
                                   ("splat_slam_ros.geometry", "splat_slam_ros.io.a"),
                                   ("splat_slam_ros.io.a", "splat_slam_ros.mapping.m"),
                                   ("splat_slam_ros.tracking.t", "splat_slam_ros.depth.d")]


def test_stages_import_only_lower_stages():
    assert stage_violations(import_graph(modules())) == []


def test_no_dynamic_imports():
    found = []
    for m, (path, _) in modules().items():
        if m in DYNAMIC_IMPORT_ALLOWED:
            continue
        for n in ast.walk(ast.parse(path.read_text())):
            if isinstance(n, ast.Name) and n.id == "__import__":
                found.append((m, n.lineno, "__import__"))
            elif isinstance(n, ast.alias) and n.name.split(".")[0] == "importlib":
                found.append((m, n.lineno, "importlib"))
    assert found == []


def test_stage_nodes_do_not_import_the_tools():
    """The four stage nodes and their shared ROS plumbing (``nodes/``) stand without the
    tools (``nodes/tools/``: launcher, player, camera driver, topic tool, logger)."""
    graph = import_graph(modules())
    bad = sorted((m, d) for m, deps in graph.items() for d in deps
                 if m.startswith("splat_slam_nodes.") and not m.startswith("splat_slam_nodes.tools")
                 and d.startswith("splat_slam_nodes.tools"))
    assert bad == []
