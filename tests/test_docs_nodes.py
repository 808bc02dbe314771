"""The node reference pages (docs/nodes/*.md) checked against the code, so they cannot drift.

Everything is read from the sources with :mod:`ast` (no ROS, nothing started): for each page
the topics its node publishes and subscribes (``TOPICS``/``SERVICES`` keys resolved to names,
literal names, ``ros.*`` topic keys, command-line topic defaults, and what the SplatNode
helpers ``publishers``/``route``/``on_events`` add), with message type and QoS (the presets of
nodes/qos.py, ``events_qos``, ``tf_qos``...); its services; its node options (``node.*``, its
``NODE_OPTIONS`` entry in nodes/node_options.py and literal ``declare_parameter`` names); the
``ros.*_frame`` keys it uses; its exit statuses; and the command-line options of
``build_parser``. Each must appear, backticked, in the right section and table row of the
page: a new topic, option or QoS change without documentation fails here.
"""
import ast
import functools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Set, Tuple

import pytest

REPO = Path(__file__).resolve().parents[1]
NODES = REPO / "nodes"
DOCS = REPO / "docs" / "nodes"

# page -> the modules whose code it documents (the node module first)
PAGES: Dict[str, Tuple[str, ...]] = {
    "tracker.md": ("tracker_node.py", "camera_input.py", "tf_frames.py"),
    "depth.md": ("depth_node.py",),
    "loop_closure.md": ("loop_closure_node.py",),
    "mapper.md": ("mapper_node.py", "map_services.py"),
    "rerun_logger.md": ("tools/rerun_logger.py",),
    "player.md": ("tools/bag_player.py",),
    "camera.md": ("tools/camera_node.py",),
    "launcher.md": ("tools/launch.py",),
}
# calls whose topic is computed at run time (the bag's own topic names): documented by hand
DYNAMIC_TOPICS = {("tools/bag_player.py", "create_publisher")}
# the least a page's code must yield (pubs, subs, services, node options, CLI options): an
# extractor that silently finds nothing fails here instead of passing every page
MINIMUM = {
    "tracker.md": (9, 4, 0, 10, 0),
    "depth.md": (2, 3, 0, 4, 0),
    "loop_closure.md": (3, 3, 0, 4, 0),
    "mapper.md": (10, 5, 3, 10, 0),
    "rerun_logger.md": (1, 10, 0, 8, 0),
    "player.md": (2, 2, 0, 0, 18),
    "camera.md": (3, 1, 0, 0, 13),
    "launcher.md": (1, 1, 0, 0, 25),
}
SECTIONS = {"pub": "Published topics", "sub": "Subscribed topics", "srv": "Services"}
# entry points that return a process's exit status (ints returned there are documented)
EXIT_FUNCS = {"main", "run", "play", "spin", "run_node", "run_rclpy_tool", "supervise"}


# --------------------------------------------------------------------------- QoS
@dataclass(frozen=True)
class QoS:
    reliable: bool
    transient_local: bool
    depth: int

    def text(self) -> str:
        """How a page writes it: ``RELIABLE, TRANSIENT_LOCAL, depth 200``."""
        return (f"{'RELIABLE' if self.reliable else 'BEST_EFFORT'}, "
                f"{'TRANSIENT_LOCAL' if self.transient_local else 'VOLATILE'}, depth {self.depth}")


def _parse(name: str, text: Optional[str] = None) -> ast.Module:
    return ast.parse(text if text is not None else (NODES / name).read_text())


def _functions(tree: ast.AST) -> Dict[str, ast.FunctionDef]:
    return {n.name: n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}


def _profile_call(fn: ast.FunctionDef) -> QoS:
    """The QoS of a function ``return QoSProfile(depth=.., reliability=.., durability=..)``."""
    call = next(n for n in ast.walk(fn) if isinstance(n, ast.Call) and
                getattr(n.func, "id", "") == "QoSProfile")
    kw = {k.arg: k.value for k in call.keywords}
    return QoS(kw["reliability"].attr == "RELIABLE", kw["durability"].attr == "TRANSIENT_LOCAL",
               int(kw["depth"].value))


def qos_table() -> Dict[str, QoS]:
    """QoS factory name -> QoS: qos.py's presets (``keyframe_qos``...), events_qos, tf_qos,
    tf_static_qos and rclpy's ``qos_profile_sensor_data``."""
    out: Dict[str, QoS] = {}
    for node in ast.walk(_parse("qos.py")):
        if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", "") == "PRESETS":
            for k, v in zip(node.value.keys, node.value.values):
                rel, tl, depth = (a.value for a in v.args[:3])
                out[f"{k.value}_qos"] = QoS(bool(rel), bool(tl), int(depth))
    out["events_qos"] = _profile_call(_functions(_parse("node_common.py"))["events_qos"])
    tf = _functions(_parse("tf_frames.py"))
    out["tf_qos"] = _profile_call(tf["tf_qos"])
    out["tf_static_qos"] = _profile_call(tf["tf_static_qos"])
    out["qos_profile_sensor_data"] = QoS(False, False, 5)      # rclpy's SensorData profile
    return out


# --------------------------------------------------------------------------- names
def _literal(node: ast.AST, consts: Dict[str, str]) -> Optional[str]:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        parts = []
        for v in node.values:
            if isinstance(v, ast.Constant):
                parts.append(str(v.value))
            elif isinstance(v, ast.FormattedValue) and getattr(v.value, "id", None) in consts:
                parts.append(consts[v.value.id])
            else:
                return None
        return "".join(parts)
    return None


def name_tables() -> Tuple[Dict[str, str], Dict[str, str]]:
    """TOPICS and SERVICES of node_common.py, keys resolved to names."""
    tree = _parse("node_common.py")
    consts: Dict[str, str] = {}
    tables: Dict[str, Dict[str, str]] = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            target = node.targets[0].id
            if isinstance(node.value, ast.Dict):
                tables[target] = {k.value: _literal(v, consts)
                                  for k, v in zip(node.value.keys, node.value.values)}
            elif _literal(node.value, consts) is not None:
                consts[target] = _literal(node.value, consts)
    return tables["TOPICS"], tables["SERVICES"]


def ros_fields() -> Set[str]:
    """The fields of the ``ros`` configuration section (RosConfig in splat_slam_ros/config.py)."""
    tree = ast.parse((REPO / "splat_slam_ros" / "config.py").read_text())
    cls = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "RosConfig")
    return {n.target.id for n in cls.body if isinstance(n, ast.AnnAssign)}


def msg_imports(tree: ast.AST) -> Dict[str, str]:
    """Imported message / service classes: ``Image`` -> ``sensor_msgs/msg/Image``."""
    out = {}
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom) and n.module and n.module.split(".")[-1] in ("msg", "srv"):
            pkg, kind = n.module.split(".")[0], n.module.split(".")[-1]
            for a in n.names:
                out[a.asname or a.name] = f"{pkg}/{kind}/{a.name}"
    return out


# --------------------------------------------------------------------------- argparse
@dataclass
class Option:
    names: Tuple[str, ...]          # option strings, or the positional's name
    dest: str
    default: object = None
    has_default: bool = False       # a default worth stating (not a flag, not None / [])
    hidden: bool = False            # help=argparse.SUPPRESS


def cli_options(tree: ast.AST) -> List[Option]:
    """The ``add_argument`` calls of the module's ``build_parser``."""
    fn = _functions(tree).get("build_parser")
    if fn is None:
        return []
    out = []
    for n in ast.walk(fn):
        if not (isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "add_argument"):
            continue
        names = tuple(a.value for a in n.args if isinstance(a, ast.Constant))
        kw = {k.arg: k.value for k in n.keywords}
        dest = kw["dest"].value if "dest" in kw else names[-1].lstrip("-").replace("-", "_")
        action = kw["action"].value if "action" in kw else "store"
        default = ast.literal_eval(kw["default"]) if "default" in kw else None
        out.append(Option(names, dest, default,
                          action == "store" and default not in (None, [], ""),
                          getattr(kw.get("help"), "attr", "") == "SUPPRESS"))
    return out


# --------------------------------------------------------------------------- endpoints
@dataclass(frozen=True)
class Endpoint:
    kind: str                       # pub / sub / srv
    name: str                       # topic or service name, or a ros.* key
    type: Optional[str]             # pkg/msg/Type, None when computed at run time
    qos: Tuple[QoS, ...]            # alternatives (e.g. node.input_qos); () for services


@dataclass
class NodeCode:
    endpoints: Set[Endpoint] = field(default_factory=set)
    options: Dict[str, object] = field(default_factory=dict)     # node.* -> default
    used_options: Set[str] = field(default_factory=set)
    params: Set[str] = field(default_factory=set)                # other declared parameters
    frames: Set[str] = field(default_factory=set)                # ros.*_frame keys
    cli: List[Option] = field(default_factory=list)
    exit_codes: Set[int] = field(default_factory=set)
    unresolved: List[str] = field(default_factory=list)
    splat_node: bool = False


CALLS = {"create_publisher": ("pub", 1, 2), "create_subscription": ("sub", 1, 3),
         "subscribe": ("sub", 1, 2), "create_service": ("srv", 1, None)}


class Extractor:
    def __init__(self):
        self.topics, self.services = name_tables()
        self.qos = qos_table()
        self.ros = ros_fields()
        common = _parse("node_common.py")
        self.common_types = msg_imports(common)
        fns = _functions(common)
        self.common_fns = fns
        base = next(n for n in common.body if isinstance(n, ast.ClassDef) and
                    n.name == "SplatNode")
        self.splat_init = _functions(base)["__init__"]
        # SplatNode.publishers: {channel: (type, topic, qos)}; route: the same per kwarg
        self.publish_spec = self._spec_dict(fns["publishers"])
        self.route_spec = {}
        for n in ast.walk(fns["route"]):
            if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "sub":
                self.route_spec[n.args[1].value] = (
                    self.common_types[n.args[0].id], self.topics[n.args[1].value],
                    (self._qos_of(n.args[2], fns["route"]),))

    def _spec_dict(self, fn) -> Dict[str, tuple]:
        d = next(n for n in ast.walk(fn) if isinstance(n, ast.Dict))
        return {k.value: (self.common_types[v.elts[0].id], self.topics[v.elts[1].slice.value],
                          (self._qos_of(v.elts[2], fn),))
                for k, v in zip(d.keys, d.values)}

    # ------------------------------------------------------------ resolution
    def _qos_of(self, node: ast.AST, fn: Optional[ast.AST]) -> Optional[QoS]:
        alts = self._qos_alts(node, fn)
        return alts[0] if alts and len(alts) == 1 else None

    def _qos_alts(self, node: ast.AST, fn: Optional[ast.AST]) -> Optional[Tuple[QoS, ...]]:
        if isinstance(node, ast.Constant) and isinstance(node.value, int):
            return (QoS(True, False, node.value),)            # rclpy: a depth, RELIABLE
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
            if name == "qos" and node.args:
                name = f"{node.args[0].value}_qos"
            return (self.qos[name],) if name in self.qos else None
        if isinstance(node, ast.Name):
            if node.id in self.qos:
                return (self.qos[node.id],)
            for a in ast.walk(fn) if fn is not None else ():
                if isinstance(a, ast.Assign) and getattr(a.targets[0], "id", "") == node.id:
                    return self._qos_alts(a.value, fn)
        if isinstance(node, ast.IfExp):
            a, b = self._qos_alts(node.body, fn), self._qos_alts(node.orelse, fn)
            return a + b if a and b else None
        return None

    def _name_of(self, node: ast.AST, cli: Dict[str, Option]) -> Optional[str]:
        lit = _literal(node, {})
        if lit is not None:
            return lit
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and \
                node.value.id in ("TOPICS", "SERVICES"):
            table = self.topics if node.value.id == "TOPICS" else self.services
            return table[node.slice.value]
        if isinstance(node, ast.Attribute):
            if getattr(node.value, "id", "") in ("args", "a") and node.attr in cli:
                d = cli[node.attr].default           # a command-line topic: its default
                return d if isinstance(d, str) else None
            if node.attr in self.ros and _is_ros_section(node.value):
                return f"ros.{node.attr}"
        return None

    # ------------------------------------------------------------ a page's code
    def node_code(self, sources: Dict[str, str]) -> NodeCode:
        code = NodeCode()
        trees = {name: _parse(name, text) for name, text in sources.items()}
        for tree in trees.values():
            code.cli += cli_options(tree)
        cli = {o.dest: o for o in code.cli}
        for name, tree in trees.items():
            types = {**self.common_types, **msg_imports(tree)}
            for fn in [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)]:
                self._function(name, fn, types, cli, code)
            for n in ast.walk(tree):
                if isinstance(n, ast.ClassDef) and any(getattr(b, "id", "") == "SplatNode"
                                                       for b in n.bases):
                    self._splat_node(n, code)
                if isinstance(n, ast.Attribute) and n.attr in self.ros and \
                        n.attr.endswith("_frame") and _is_ros_section(n.value):
                    code.frames.add(f"ros.{n.attr}")
                if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "SystemExit" and \
                        n.args and isinstance(n.args[0], ast.Constant):
                    code.exit_codes.add(n.args[0].value)
                if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "run_rclpy_tool":
                    tool = _functions(_parse("tool_runner.py"))["run_rclpy_tool"]
                    code.exit_codes |= _returned_ints(tool)
        if code.splat_node:
            code.exit_codes |= _returned_ints(self.common_fns["run_node"])
        return code

    def _function(self, module, fn, types, cli, code: NodeCode) -> None:
        for n in ast.walk(fn):
            if isinstance(n, ast.Return) and fn.name in EXIT_FUNCS and \
                    isinstance(n.value, ast.Constant) and isinstance(n.value.value, int):
                code.exit_codes.add(n.value.value)
            if isinstance(n, ast.Subscript) and getattr(n.value, "attr", "") == "opts":
                code.used_options.add(n.slice.value)
            if not isinstance(n, ast.Call) or not isinstance(n.func, ast.Attribute):
                continue
            attr = n.func.attr
            if attr == "declare_parameter" and isinstance(n.args[0], ast.Constant):
                p = n.args[0].value
                if p.startswith("node."):
                    code.options[p[len("node."):]] = ast.literal_eval(n.args[1])
                else:
                    code.params.add(p)
            if getattr(n.func.value, "id", "") == "self" and attr in ("publishers", "route",
                                                                       "on_events"):
                self._helper(attr, n, code)
                continue
            if attr == "subscribe_image":      # SplatNode's camera subscription: either type
                name, qos = self._name_of(n.args[0], cli), self._qos_alts(n.args[1], fn)
                if name is None or qos is None:
                    code.unresolved.append(f"{module}:{n.lineno} {attr}")
                    continue
                for typ in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"):
                    code.endpoints.add(Endpoint("sub", name, typ, qos))
                continue
            if attr not in CALLS or len(n.args) < 2:
                continue
            kind, i_name, i_qos = CALLS[attr]
            name = self._name_of(n.args[i_name], cli)
            typs = self._types_of(n.args[0], fn, types)
            qos = () if i_qos is None else self._qos_alts(n.args[i_qos], fn)
            if name is None or not typs or qos is None:
                if (module, attr) not in DYNAMIC_TOPICS:
                    code.unresolved.append(f"{module}:{n.lineno} {attr}")
                continue
            for typ in typs:
                code.endpoints.add(Endpoint(kind, name, typ, qos))

    @staticmethod
    def _types_of(node: ast.AST, fn: ast.AST, types: Dict[str, str]) -> Tuple[str, ...]:
        """A message class argument's type names: an imported class, or a local chosen
        between two of them (``t = A if cond else B``: both)."""
        if getattr(node, "id", "") in types:
            return (types[node.id],)
        for a in ast.walk(fn) if isinstance(node, ast.Name) else ():
            if isinstance(a, ast.Assign) and getattr(a.targets[0], "id", "") == node.id and \
                    isinstance(a.value, ast.IfExp):
                alts = [types.get(getattr(x, "id", "")) for x in (a.value.body, a.value.orelse)]
                return tuple(alts) if all(alts) else ()
        return ()

    def _helper(self, attr: str, call: ast.Call, code: NodeCode) -> None:
        """What SplatNode.publishers / route / on_events create for the calling node."""
        events = Endpoint("sub", self.topics["events"], "std_msgs/msg/String",
                          (self.qos["events_qos"],))
        if attr == "publishers":
            for a in call.args:
                t, name, q = self.publish_spec[a.value]
                code.endpoints.add(Endpoint("pub", name, t, q))
            return
        code.endpoints.add(events)
        if attr == "route":
            for k in call.keywords:
                if k.arg in self.route_spec and isinstance(k.value, ast.Constant) and k.value.value:
                    t, name, q = self.route_spec[k.arg]
                    code.endpoints.add(Endpoint("sub", name, t, q))

    def _splat_node(self, cls: ast.ClassDef, code: NodeCode) -> None:
        """Options of ``super().__init__(name, NODE_OPTIONS[name])`` (node_options.py) + what
        SplatNode.__init__ declares (``{**COMMON_OPTIONS, **options}``)."""
        from splat_slam_nodes.node_options import COMMON_OPTIONS, NODE_OPTIONS
        code.splat_node = True
        for n in ast.walk(cls):
            if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "__init__" and \
                    len(n.args) == 2 and isinstance(n.args[1], ast.Subscript) and \
                    getattr(n.args[1].value, "id", "") == "NODE_OPTIONS":
                code.options.update(NODE_OPTIONS[n.args[1].slice.value])
        init = self.splat_init
        for n in ast.walk(init):
            if isinstance(n, ast.Dict) and n.keys and None in n.keys and any(
                    getattr(v, "id", "") == "COMMON_OPTIONS" for v in n.values):
                code.options.update(COMMON_OPTIONS)
            if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "declare_parameter" \
                    and isinstance(n.args[0], ast.Constant):
                code.params.add(n.args[0].value)
            if isinstance(n, ast.Call) and getattr(n.func, "attr", "") == "create_publisher":
                code.endpoints.add(Endpoint("pub", self._name_of(n.args[1], {}),
                                            self.common_types[n.args[0].id],
                                            self._qos_alts(n.args[2], init)))
        code.frames.add("ros.map_frame")            # SplatNode.frame_id: every header


def _is_ros_section(node: ast.AST) -> bool:
    """``<...>.ros`` or a local named ``r`` / ``ros`` (tf_frames: ``r = owner.cfg.ros``)."""
    return getattr(node, "attr", None) == "ros" or getattr(node, "id", None) in ("r", "ros")


def _returned_ints(fn: ast.FunctionDef) -> Set[int]:
    out = {n.value.value for n in ast.walk(fn) if isinstance(n, ast.Return) and
           isinstance(n.value, ast.Constant) and isinstance(n.value.value, int)}
    out |= {d.value for d in fn.args.defaults if isinstance(d, ast.Constant) and
            isinstance(d.value, int) and not isinstance(d.value, bool)}
    return out


# --------------------------------------------------------------------------- the pages
def sections(text: str) -> Dict[str, str]:
    """``## Heading`` -> its text (up to the next ``##``)."""
    out, cur = {}, None
    for line in text.splitlines():
        if line.startswith("## "):
            cur = line[3:].strip()
            out[cur] = ""
        elif cur is not None:
            out[cur] += line + "\n"
    return out


def rows(section: str) -> List[List[str]]:
    return [[c.strip() for c in line.strip().strip("|").split("|")]
            for line in section.splitlines() if line.strip().startswith("|")]


def find_row(section: str, name: str) -> Optional[List[str]]:
    """The table row whose first cell names ``name`` in backticks."""
    for r in rows(section):
        if f"`{name}`" in r[0]:
            return r
    return None


def _value_text(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def default_shown(cell: str, default) -> bool:
    """The cell gives ``default`` in backticks (strings may be quoted, numbers 2 or 2.0)."""
    for tok in re.findall(r"`([^`]*)`", cell):
        tok = tok.strip().strip("'\"") if isinstance(default, str) else tok.strip()
        if isinstance(default, bool) or isinstance(default, str):
            if tok == _value_text(default):
                return True
        else:
            try:
                if float(tok) == float(default):
                    return True
            except ValueError:
                pass
    return False


def problems(code: NodeCode, text: str) -> List[str]:
    """What the page lacks or states differently from the code (empty: it is complete)."""
    sec = sections(text)
    out: List[str] = []

    def need(title: str) -> str:
        for k, v in sec.items():
            if k.startswith(title):
                return v
        out.append(f"no section '## {title}'")
        return ""

    out += [f"cannot resolve the topic, type or QoS of {u}" for u in sorted(set(code.unresolved))]
    for e in sorted(code.endpoints, key=lambda e: (e.kind, e.name)):
        row = find_row(need(SECTIONS[e.kind]), e.name)
        if row is None:
            out.append(f"{SECTIONS[e.kind]}: no row for `{e.name}` ({e.type})")
            continue
        if len(row) < 3 or f"`{e.type}`" not in row[1]:
            out.append(f"{SECTIONS[e.kind]}: `{e.name}` should give the type `{e.type}`")
        for q in e.qos:
            if q.text() not in row[2]:
                out.append(f"{SECTIONS[e.kind]}: `{e.name}` should give the QoS '{q.text()}'")
    if code.splat_node:
        params = need("Parameters")
        for key, default in sorted(code.options.items()):
            row = find_row(params, f"node.{key}")
            if row is None:
                out.append(f"Parameters: no row for `node.{key}`")
            elif len(row) < 2 or not default_shown(row[1], default):
                out.append(f"Parameters: `node.{key}` should give the default "
                           f"`{_value_text(default)}`")
        for p in sorted(code.params | {"config_file"}):
            if f"`{p}`" not in params:
                out.append(f"Parameters: `{p}` is not mentioned")
        if "(../configuration.md)" not in params:
            out.append("Parameters: no link to ../configuration.md (every configuration key "
                       "is a parameter)")
        for k in sorted(code.used_options - set(code.options)):
            out.append(f"node.{k} is used but never declared (code bug?)")
    if code.frames:
        tf = need("TF frames")
        out += [f"TF frames: `{f}` is not mentioned" for f in sorted(code.frames)
                if f"`{f}`" not in tf]
    if code.cli:
        opts = need("Command-line options")
        for o in code.cli:
            if o.hidden:
                continue
            label = o.names[0]                   # --option, or the positional's name
            row = find_row(opts, label) or (None if label.startswith("-") else
                                             find_row(opts, label.upper()))
            if row is None:
                out.append(f"Command-line options: no row for `{label}`")
            elif o.has_default and (len(row) < 2 or not default_shown(row[1], o.default)):
                out.append(f"Command-line options: `{label}` should give the default "
                           f"`{_value_text(o.default)}`")
    if code.exit_codes:
        ex = need("Exit status")
        out += [f"Exit status: `{c}` is not explained" for c in sorted(code.exit_codes)
                if f"`{c}`" not in ex]
    if "## Run it alone" not in text:
        out.append("no section '## Run it alone'")
    return list(dict.fromkeys(out))                 # each problem once


@functools.lru_cache(maxsize=1)
def extractor() -> Extractor:
    return Extractor()


def page_code(page: str, overrides: Optional[Dict[str, str]] = None) -> NodeCode:
    """What the code of ``page``'s modules holds (``overrides``: module -> replaced source)."""
    srcs = {m: (overrides or {}).get(m, (NODES / m).read_text()) for m in PAGES[page]}
    code = extractor().node_code(srcs)
    if page == "launcher.md":           # the statuses its docstring promises (3: no result)
        doc = ast.get_docstring(_parse("tools/launch.py")) or ""
        para = doc.split("Exit status:", 1)[1].split("\n\n", 1)[0]
        code.exit_codes |= {int(x) for x in re.findall(r"(?<![\w.-])(\d+)(?= )", para)}
    return code


# --------------------------------------------------------------------------- tests

@pytest.mark.parametrize("page", sorted(PAGES))
def test_page_documents_the_code(page):
    path = DOCS / page
    assert path.is_file(), f"{path.relative_to(REPO)} is missing"
    code = page_code(page)
    found = (sum(e.kind == "pub" for e in code.endpoints),
             sum(e.kind == "sub" for e in code.endpoints),
             sum(e.kind == "srv" for e in code.endpoints),
             len(code.options), sum(not o.hidden for o in code.cli))
    assert all(f >= m for f, m in zip(found, MINIMUM[page])), \
        f"the extractor found only {found} (pubs, subs, services, options, CLI) for {page}, " \
        f"expected at least {MINIMUM[page]}: is it still reading the code?"
    bad = problems(code, path.read_text())
    assert not bad, f"docs/nodes/{page} does not match the code:\n  " + "\n  ".join(bad)


def test_index_links_every_page_and_names_every_topic():
    text = (DOCS / "README.md").read_text()
    topics, services = name_tables()
    missing = [p for p in PAGES if f"({p})" not in text]
    missing += [t for t in list(topics.values()) + list(services.values())
                if not re.search(rf"{re.escape(t)}(?![\w/])", text)]
    assert not missing, f"docs/nodes/README.md lacks: {', '.join(missing)}"


def test_qos_presets_are_read():
    q = qos_table()
    assert q["keyframe_qos"] == QoS(True, True, 200)
    assert q["sensor_qos"].reliable is False and q["events_qos"].transient_local is True
    assert len(q) >= 12


TRACKER_EXTRA = '''

def _undocumented(self):
    self.node.create_publisher(String, "/splat/undocumented_topic", status_qos())
    self.subscribe(Image, TOPICS["view_rgb"], Q.rendered_qos(), None, "x")
    self.node.declare_parameter("node.undocumented_option", 3)
'''


def test_an_undocumented_addition_fails():
    """A topic, a subscription and an option added to the tracker without documentation:
    the page check reports each of them (the same text as on the real files)."""
    src = (NODES / "tracker_node.py").read_text() + TRACKER_EXTRA
    src = src.replace("from .node_common import", "from std_msgs.msg import String\n"
                      "from sensor_msgs.msg import Image\nfrom .node_common import", 1)
    code = page_code("tracker.md", {"tracker_node.py": src})
    bad = "\n".join(problems(code, (DOCS / "tracker.md").read_text()))
    assert "`/splat/undocumented_topic`" in bad
    assert "Subscribed topics: no row for `/splat/map/view_rgb`" in bad
    assert "`node.undocumented_option`" in bad
    # and a changed QoS preset
    src = (NODES / "tracker_node.py").read_text().replace("Q.pose_qos()", "Q.status_qos()")
    code = page_code("tracker.md", {"tracker_node.py": src})
    bad = "\n".join(problems(code, (DOCS / "tracker.md").read_text()))
    assert "`/splat/camera_pose` should give the QoS 'RELIABLE, TRANSIENT_LOCAL, depth 1'" in bad
