"""Packaging: ``pip install .`` installs what the code imports.

- every third-party module the installed packages import is a declared dependency: module-level
  imports in setup.cfg ``install_requires``, imports inside functions there or in an extra;
  ROS 2 modules (not pip-installed by setup.cfg) are ``exec_depend``s of package.xml instead;
- every ``install_requires`` distribution has its rosdep key in package.xml;
- importing a console-script entry module imports none of the extras' modules (so every
  command starts without them);
- setup.cfg and requirements.txt pin the packages they share alike; torch stays pinned.
"""
import ast
import configparser
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Dict, Iterator, List, Set, Tuple

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

REPO = Path(__file__).resolve().parents[1]

# import name -> the distribution(s) that provide it, where the names differ. open3d: one
# build per platform (setup.cfg lists both, with markers), both must be declared.
IMPORT_TO_DIST: Dict[str, Tuple[str, ...]] = {
    "cv2": ("opencv-python-headless",),
    "yaml": ("pyyaml",),
    "pytorch_msssim": ("pytorch-msssim",),
    "mcap_ros2": ("mcap-ros2-support",),
    "rerun": ("rerun-sdk",),
    "open3d": ("open3d-cpu", "open3d"),
    "skimage": ("scikit-image",),
    "sklearn": ("scikit-learn",),
    "PIL": ("pillow",),
}
# ROS 2 Python packages: from a ROS 2 Jazzy install (package.xml) or the ros-jazzy-* wheels and
# the msg_defs/ build (./run.sh), never from install_requires
ROS_MODULES = {"rclpy", "rcl_interfaces", "builtin_interfaces", "rosgraph_msgs", "std_msgs",
               "std_srvs", "sensor_msgs", "geometry_msgs", "nav_msgs", "tf2_msgs",
               "visualization_msgs", "splat_slam_msgs"}
# install_requires distribution -> rosdep key (rosdistro rosdep/python.yaml); default
# python3-<name>-pip, rosdep's naming for packages installed from PyPI
DIST_TO_ROSDEP = {
    "torch": "python3-torch", "numpy": "python3-numpy", "scipy": "python3-scipy",
    "opencv-python-headless": "python3-opencv", "pyyaml": "python3-yaml",
    "tqdm": "python3-tqdm", "matplotlib": "python3-matplotlib", "lz4": "python3-lz4",
    "zstandard": "python3-zstandard", "open3d-cpu": "python3-open3d-pip",
    "open3d": "python3-open3d-pip",
}

Import = Tuple[str, bool, str]       # (top-level name, at module level, "file:line")


# ------------------------------------------------------------------ project metadata
def setup_cfg() -> configparser.ConfigParser:
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    return cfg


def requirements(text: str) -> List[Requirement]:
    """Requirement lines (setup.cfg values or a requirements file; comments, options skipped)."""
    out = []
    for line in text.splitlines():
        line = line.split(" #")[0].strip()
        if line and not line.startswith(("#", "-")):
            out.append(Requirement(line))
    return out


def install_requires() -> List[Requirement]:
    return requirements(setup_cfg()["options"]["install_requires"])


def extras() -> Dict[str, List[Requirement]]:
    return {k: requirements(v) for k, v in setup_cfg()["options.extras_require"].items()}


def package_dirs() -> Dict[str, Path]:
    """{installed top-level package: its source folder}, from setup.py's package_dir."""
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "package_dir":
            return {k: REPO / v for k, v in ast.literal_eval(node.value).items() if k}
    raise AssertionError("setup.py has no package_dir")


def entry_modules() -> List[str]:
    lines = setup_cfg()["options.entry_points"]["console_scripts"].strip().splitlines()
    return sorted({ln.split("=", 1)[1].strip().split(":")[0] for ln in lines if ln.strip()})


def exec_depends() -> Set[str]:
    root = ET.parse(REPO / "package.xml").getroot()
    return {e.text.strip() for tag in ("depend", "exec_depend") for e in root.findall(tag)}


def dists_of(module: str) -> Tuple[str, ...]:
    return tuple(canonicalize_name(d) for d in IMPORT_TO_DIST.get(module, (module,)))


def modules_of(dist: str) -> List[str]:
    dist = canonicalize_name(dist)
    names = [m for m, ds in IMPORT_TO_DIST.items() if dist in dists_of(m)]
    return names or [dist.replace("-", "_")]


# ------------------------------------------------------------------ imports in the source
def third_party_imports(path: Path, label: str, first_party: Set[str]) -> Iterator[Import]:
    """Absolute imports of third-party modules in one file; module level = outside any
    function (a class body, ``try`` or ``if`` at module level runs at import too)."""
    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            names = []
            if isinstance(child, ast.Import):
                names = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                names = [child.module]
            for name in names:
                top = name.split(".")[0]
                if top not in sys.stdlib_module_names and top not in first_party \
                        and top != "__future__":
                    yield top, not in_function, f"{label}:{child.lineno}"
            yield from visit(child, nested)
    yield from visit(ast.parse(path.read_text(), str(path)), False)


def project_imports() -> List[Import]:
    dirs = package_dirs()
    out = []
    for pkg, root in dirs.items():
        for path in sorted(root.rglob("*.py")):
            out += third_party_imports(path, str(path.relative_to(REPO)), set(dirs))
    return out


def undeclared(imports: List[Import], required: List[Requirement],
               optional: Dict[str, List[Requirement]]) -> List[str]:
    """One line per import whose distribution is not declared where it has to be."""
    req = {canonicalize_name(r.name) for r in required}
    opt = {canonicalize_name(r.name) for rs in optional.values() for r in rs}
    problems = []
    for name, module_level, where in imports:
        if name in ROS_MODULES:
            continue
        allowed = req if module_level else req | opt
        missing = [d for d in dists_of(name) if d not in allowed]
        if missing and module_level and not set(missing) - opt:
            problems.append(f"{where}: module-level import of {name}, from an extra "
                            f"({', '.join(missing)}): import it inside the function that uses it")
        elif missing:
            where_to = "install_requires" + ("" if module_level else " or an extra")
            problems.append(f"{where}: import {name}: {', '.join(missing)} not in setup.cfg "
                            f"{where_to} (or map the import name in IMPORT_TO_DIST)")
    return problems


# ------------------------------------------------------------------ tests
def test_import_scan_finds_undeclared_and_misplaced_dependencies(tmp_path):
    src = tmp_path / "mod.py"
    src.write_text("import os\nimport numpy\nfrom cv2 import imread\nimport rerun as rr\n"
                   "from . import sibling\nimport rclpy\n"
                   "def f():\n    import skimage.io\n    import onnxruntime\n    import mine.sub\n")
    imports = list(third_party_imports(src, "mod.py", {"mine"}))
    assert [(n, top) for n, top, _ in imports] == [
        ("numpy", True), ("cv2", True), ("rerun", True), ("rclpy", True),
        ("skimage", False), ("onnxruntime", False)]
    req = requirements("numpy\nopencv-python-headless")
    opt = {"onnx": requirements("onnxruntime"), "rerun": requirements("rerun-sdk")}
    problems = undeclared(imports, req, opt)
    assert len(problems) == 2, problems
    assert "module-level import of rerun" in problems[0]
    assert "scikit-image not in setup.cfg install_requires or an extra" in problems[1]


def test_every_third_party_import_is_a_declared_dependency():
    imports = project_imports()
    names = {n for n, _, _ in imports}
    assert {"torch", "numpy", "cv2", "rclpy"} <= names      # the scan sees the packages
    problems = undeclared(imports, install_requires(), extras())
    assert not problems, "\n".join(problems)


def test_ros_imports_are_package_xml_dependencies():
    imported = {n for n, _, _ in project_imports()} & ROS_MODULES
    assert imported, "no ROS import found: is the scan broken?"
    missing = sorted(imported - exec_depends())
    assert not missing, f"add <exec_depend> for these to package.xml: {missing}"


def test_install_requires_have_rosdep_keys_in_package_xml():
    dists = {canonicalize_name(r.name) for r in install_requires()}
    keys = {d: DIST_TO_ROSDEP.get(d, f"python3-{d}-pip") for d in dists}
    missing = {d: k for d, k in keys.items() if k not in exec_depends()}
    assert missing == {}, f"add <exec_depend> for these to package.xml: {missing}"


def test_extras_table_matches_setup_cfg():
    from splat_slam_ros.extras import EXTRAS
    cfg = {k: sorted(canonicalize_name(r.name) for r in rs) for k, rs in extras().items()}
    assert cfg == {k: [canonicalize_name(v)] for k, v in EXTRAS.items()}


def test_readme_names_every_extra():
    readme = (REPO / "README.md").read_text()
    assert [k for k in extras() if f".[{k}]" not in readme] == []


ENTRY_IMPORT_SCRIPT = """
import importlib, json, sys
mods, optional = json.loads(sys.argv[1]), json.loads(sys.argv[2])
found, seen = {}, set()
for m in mods:
    importlib.import_module(m)
    new = sorted(o for o in optional if o in sys.modules and o not in seen)
    seen.update(new)
    if new:
        found[m] = new
print(json.dumps(found))
"""


def test_entry_modules_import_without_the_extras():
    """Each console script's module, imported in one fresh interpreter: the first one that
    pulls in an extra's module is named with it."""
    optional = sorted({m for rs in extras().values() for r in rs for m in modules_of(r.name)})
    assert "onnxruntime" in optional and "rerun" in optional
    mods = entry_modules()
    assert len(mods) >= 10
    r = subprocess.run([sys.executable, "-c", ENTRY_IMPORT_SCRIPT, json.dumps(mods),
                        json.dumps(optional)], cwd=REPO, capture_output=True, text=True,
                       timeout=600, stdin=subprocess.DEVNULL)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    found = json.loads(r.stdout.strip().splitlines()[-1])
    assert not found, f"entry module -> the extras' modules it imports (import on use): {found}"


def pins(reqs: List[Requirement]) -> Dict[str, Set[Tuple[Tuple[str, ...], str]]]:
    out: Dict[str, Set[Tuple[Tuple[str, ...], str]]] = {}
    for r in reqs:
        out.setdefault(canonicalize_name(r.name), set()).add(
            (tuple(sorted(str(s) for s in r.specifier)), str(r.marker or "")))
    return out


def test_pins_agree_with_requirements_txt():
    cfg = pins(install_requires() + [r for rs in extras().values() for r in rs])
    txt = pins(requirements((REPO / "requirements.txt").read_text()))
    shared = sorted(set(cfg) & set(txt))
    assert {"torch", "numpy", "open3d-cpu", "rerun-sdk", "pytorch-msssim"} <= set(shared)
    differ = {n: (cfg[n], txt[n]) for n in shared if cfg[n] != txt[n]}
    assert not differ, f"setup.cfg vs requirements.txt (specifiers, marker): {differ}"
    torch_pins = [s for specs, _ in cfg["torch"] for s in specs]
    assert torch_pins and all(s.startswith("==") for s in torch_pins), \
        f"torch must stay pinned (==) in setup.cfg, as requirements.txt pins it: {torch_pins}"
