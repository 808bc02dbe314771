"""Code-shape rules of the package and the nodes (issue 9): no module over 800 lines, no
function over 120 lines, no import circles (module-level and function-level imports), no
dynamic imports except the rasterizer's loader of its JIT-built extension (a .so by path)."""
import ast
from pathlib import Path
from typing import Dict, List, Set, Tuple

REPO = Path(__file__).resolve().parents[1]
ROOTS = {"splat_slam_ros": REPO / "splat_slam_ros", "splat_slam_nodes": REPO / "nodes"}
MAX_FILE_LINES = 800
MAX_FUNCTION_LINES = 120
DYNAMIC_IMPORT_ALLOWED = {"splat_slam_ros.mapping.rasterizer.kernel"}


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


def test_file_and_function_sizes():
    long_files, long_funcs = [], []
    for m, (path, _) in modules().items():
        text = path.read_text()
        if text.count("\n") > MAX_FILE_LINES:
            long_files.append((m, text.count("\n")))
        for n in ast.walk(ast.parse(text)):
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                size = n.end_lineno - n.lineno + 1
                if size > MAX_FUNCTION_LINES:
                    long_funcs.append((m, n.name, size))
    assert long_files == [] and long_funcs == []


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
