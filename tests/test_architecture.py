"""Import contracts and size rules (docs/architecture.md): rooms point one way, nothing imports
itself back, no file is too long and no function too tangled. `make lint` runs this file.

Every `import` counts, also the ones inside functions (a lazy import is still a dependency).
Each module belongs to the room with the longest matching prefix in RULES; a room may import
itself and the rooms listed for it, nothing else of ours. From the bottom up:

    core                 <- nothing of ours (stdlib and third-party only)
    wire                 <- core
    planner              <- core                        (pure: no devices, no clocks)
    drivers, sims        <- core, wire                  (never each other: they share only wire/)
    controller.job       <- the pure layers             (the job model)
    controller.ports     <- drivers' records, the job   (the device interfaces)
    controller.journal, .report, .motion, .align, .export   <- the pure layers and each other, downward
    controller.runtime   <- those                       (never harness, sims, the TUI or the CLI)
    controller.api, controller.repair                   <- runtime and below
    controller.harness   <- the only room of the product that imports sims/
    controller.tui, controller.cli                      <- the top (only through the API: a rule below)
    bench                <- the product (never tests/); tests <- anything
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import networkx as nx
import pytest
from radon.complexity import cc_visit

ROOT = Path(__file__).resolve().parent.parent
PRODUCT = ("core", "wire", "planner", "drivers", "sims", "controller")
PACKAGES = (*PRODUCT, "bench")
_PURE = frozenset({"core", "wire", "planner"})
_BELOW_RUNTIME = frozenset({"controller.ports", "controller.job", "controller.journal", "controller.report",
                            "controller.records",
                            "controller.motion", "controller.align", "controller.export", "controller.defaults"})
RULES: dict[str, frozenset[str]] = {
    "core": frozenset(),
    "wire": frozenset({"core"}),
    "planner": frozenset({"core"}),
    "drivers": frozenset({"core", "wire"}),
    "sims": frozenset({"core", "wire"}),
    "controller": frozenset(),   # the package's own __init__
    "controller.defaults": frozenset({"core"}),
    "controller.job": _PURE,
    "controller.ports": frozenset({"core", "wire", "drivers", "controller.job"}),
    "controller.journal": _PURE | {"controller.job"},
    "controller.report": _PURE | {"controller.journal", "controller.job", "controller.records"},
    "controller.records": _PURE,   # the shop's record store: report.json dicts and run directories only
    "controller.motion": _PURE | {"drivers", "controller.ports", "controller.job"},
    "controller.align": _PURE | {"drivers", "controller.ports", "controller.job", "controller.motion"},
    "controller.export": _PURE | {"controller.job", "controller.motion"},
    "controller.runtime": _PURE | {"drivers"} | _BELOW_RUNTIME,
    "controller.opcua": _PURE | {"controller.runtime"},
    "controller.api": _PURE | {"drivers", "controller.runtime", "controller.opcua"} | _BELOW_RUNTIME,
    "controller.repair": _PURE | {"drivers", "controller.runtime", "controller.api"} | _BELOW_RUNTIME,
    "controller.harness": _PURE | {"sims", "drivers", "controller.runtime", "controller.api", "controller.repair"}
    | _BELOW_RUNTIME,
    "controller.tui": _PURE | {"controller.api", "controller.harness", "controller.defaults"},   # the API only
    "controller.cli": _PURE | {"drivers", "controller.runtime", "controller.api", "controller.repair",
                               "controller.harness", "controller.tui", "controller.opcua"} | _BELOW_RUNTIME,
    "bench": frozenset(PRODUCT),    # a package named here grants every room inside it
}
# every module of ours lives in one of these rooms (a new top-level module of controller/ needs a line)
ROOMS = tuple(sorted(RULES, key=len, reverse=True))
MAX_TOP_MODULES = 8          # modules left at the top of controller/ besides its subpackages
MAX_LINES = 500
MAX_COMPLEXITY = 20          # radon's cyclomatic complexity (each `and`/`or` counts)


def _modules() -> dict[str, Path]:
    mods: dict[str, Path] = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = f.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = f
    return mods


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _type_only_lines(tree: ast.Module) -> set[int]:
    """Lines of imports under `if TYPE_CHECKING:`: annotations only, never run."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for sub in node.body:
                for inner in ast.walk(sub):
                    if isinstance(inner, (ast.Import, ast.ImportFrom)):
                        lines.add(inner.lineno)
    return lines


def _imports(mods: dict[str, Path]) -> list[tuple[str, int, str, bool]]:
    """(importer, line, imported module, type-only) for every import of one of our modules."""
    def resolve(name: str) -> str:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name

    out = []
    for mod, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        typing_only = _type_only_lines(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                base = node.module
                if node.level:  # relative import: resolve against the importer's package
                    pkg = mod.split(".")[: len(mod.split(".")) - node.level + (path.name == "__init__.py")]
                    base = ".".join([*pkg, node.module])
                names = [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for target in dict.fromkeys(resolve(name) for name in names):  # one entry per module imported
                if target and target != mod:
                    out.append((mod, node.lineno, target, node.lineno in typing_only))
    return out


MODS = _modules()
IMPORTS = _imports(MODS)


def room(mod: str) -> str:
    """The room a module lives in: the longest prefix of it in RULES."""
    found = next((r for r in ROOMS if _within(mod, (r,))), None)
    assert found is not None, f"{mod}: in no room of RULES (tests/test_architecture.py); give it one"
    return found


def layer_violations() -> list[str]:
    """Every import against the rooms' direction, as 'file:line: a -> b (why)'."""
    bad = []
    for mod, line, target, _typing in IMPORTS:
        src, dst = room(mod), room(target)
        if src != dst and not any(_within(dst, (g,)) for g in RULES[src]):
            where = f"{MODS[mod].relative_to(ROOT)}:{line}: {mod} -> {target}"
            bad.append(f"{where} ({src} may import {sorted(RULES[src]) or 'nothing of ours'})")
    return bad


def import_cycles(imports: list[tuple[str, int, str, bool]] | None = None) -> list[list[str]]:
    """Every cycle in the module import graph: lazy imports and imports under `if TYPE_CHECKING:`
    included (such an import never runs, but two modules that need each other's types are one
    module split in two: the shared types go to a leaf both import, e.g. a Protocol or a state
    dataclass). A package's module importing the package itself is not an edge."""
    g = nx.DiGraph()
    g.add_nodes_from(MODS)
    g.add_edges_from((m, t) for m, _, t, _typing in (IMPORTS if imports is None else imports) if not m.startswith(t + "."))
    return [sorted(c) for c in nx.simple_cycles(g)]


def test_the_contract_sees_the_code() -> None:
    """The checker finds the modules and the imports it judges (a broken walker would pass everything)."""
    assert {"core.errors", "core.config", "wire.rlp", "drivers.robot", "controller.api"} <= set(MODS)
    assert ("drivers.robot", "wire.rlp") in {(m, t) for m, _, t, _typing in IMPORTS}
    assert room("controller.runtime.build") == "controller.runtime" and room("bench.repair") == "bench"
    assert "sims" not in RULES["controller.runtime"] and "controller.harness" not in RULES["controller.runtime"]


def test_no_import_against_the_layers() -> None:
    bad = layer_violations()
    assert not bad, "imports against the layer direction (docs/architecture.md):\n" + "\n".join(bad)


# The front ends reach the controller only through its facade (docs/architecture.md "One facade"):
# the API package and its modules (controller.api: the session, what needs no session, the types
# they take and give), the harness's public face (the package controller.harness itself, never its
# modules: opening a cell, the simulators) and the shipped defaults; nothing of the rooms behind them.
# The CLI may also start the TUI (`cell tui`), the TUI never the CLI.
VIEWS = {"controller.tui": (), "controller.cli": ("controller.tui",)}
THROUGH_THE_API = ("controller.api", "controller.defaults")
HARNESS_FACE = "controller.harness"


def views_past_the_api(imports: list[tuple[str, int, str, bool]] | None = None) -> list[str]:
    """Every import by a front end of a controller module outside the facade, as 'file:line: a -> b'."""
    bad = []
    for mod, line, target, _typing in IMPORTS if imports is None else imports:
        view = next((v for v in VIEWS if _within(mod, (v,))), None)
        if view is None or not _within(target, ("controller",)) or target == HARNESS_FACE:
            continue
        if _within(target, (view, *VIEWS[view], *THROUGH_THE_API)):
            continue
        bad.append(f"{MODS[mod].relative_to(ROOT) if mod in MODS else mod}:{line}: {mod} -> {target}")
    return bad


def test_the_front_ends_reach_the_controller_only_through_the_api() -> None:
    bad = views_past_the_api()
    assert not bad, "a front end reaches past the controller's API (docs/architecture.md):\n" + "\n".join(bad)
    assert views_past_the_api([("controller.tui.x", 3, "controller.runtime.events", False),
                               ("controller.tui.x", 4, "controller.api.cell", False),
                               ("controller.tui.x", 5, "controller.harness.cell", False),
                               ("controller.tui.x", 6, "controller.harness", False),
                               ("controller.tui.x", 7, "controller.cli.main", False),
                               ("controller.cli.x", 8, "controller.job.read", False),
                               ("controller.cli.x", 9, "controller.tui.app", False),
                               ("controller.cli.x", 10, "controller.defaults", False)]) == [
        "controller.tui.x:3: controller.tui.x -> controller.runtime.events",
        "controller.tui.x:5: controller.tui.x -> controller.harness.cell",
        "controller.tui.x:7: controller.tui.x -> controller.cli.main",
        "controller.cli.x:8: controller.cli.x -> controller.job.read"]


# One wiring (docs/architecture.md "Opening a cell"): simulators are wired to a controller in one
# place. Outside controller/harness/, no file of the product, bench/ or tests/ constructs the
# controller or a set of simulators (WIRED_HERE); outside the simulators themselves, the harness and
# the driver-against-simulator tests, nobody serves simulators by hand (a SimContext).
WIRED_HERE = {"CellController": ("controller/harness/",), "SimHarness": ("controller/harness/",),
              "SimProcess": ("controller/harness/",),
              "SimContext": ("sims/", "controller/harness/", "tests/sims/", "tests/drivers/")}


def hand_wirings(files: dict[str, str] | None = None) -> list[str]:
    """Every call constructing a WIRED_HERE class outside its places, as 'file:line: Name('."""
    if files is None:
        paths = [p for pkg in (*PACKAGES, "tests") for p in sorted((ROOT / pkg).rglob("*.py"))]
        files = {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8") for p in paths}
    bad = []
    for rel, text in files.items():
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, ast.Call):
                continue
            name = node.func.id if isinstance(node.func, ast.Name) else (
                node.func.attr if isinstance(node.func, ast.Attribute) else None)
            if name in WIRED_HERE and not rel.startswith(WIRED_HERE[name]):
                bad.append(f"{rel}:{node.lineno}: {name}(")
    return bad


def test_simulators_are_wired_to_a_controller_only_by_the_harness() -> None:
    bad = hand_wirings()
    assert not bad, "open the cell with controller.harness.open_cell (docs/architecture.md):\n" + "\n".join(bad)
    assert hand_wirings({"bench/x.py": "h = SimHarness(cfg, sim)\nctl = api.CellController(cfg)\n",
                         "tests/sims/y.py": "ctx = SimContext(cell=c)\n",
                         "controller/harness/cell.py": "ctl = CellController(cfg)\n"}) == [
        "bench/x.py:1: SimHarness(", "bench/x.py:2: CellController("]


def test_no_import_cycles() -> None:
    cycles = import_cycles()
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_a_type_only_import_counts_in_a_cycle() -> None:
    """The cycle check sees `if TYPE_CHECKING:` imports: the walker marks them, the graph keeps them."""
    src = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import os\n"
    assert _type_only_lines(ast.parse(src)) == {3}
    assert import_cycles([("sims.a", 1, "sims.b", False), ("sims.b", 9, "sims.a", True)]) == [["sims.a", "sims.b"]]
    assert import_cycles([("sims.cnc.sim", 1, "sims.cnc", False), ("sims.cnc", 9, "sims.cnc.sim", False)]) == []


@pytest.mark.parametrize("pkg", ["core", "wire", "planner"])
def test_pure_layers_import_no_device_library(pkg: str) -> None:
    """core, wire and planner open no device or UI: no serial ports, Modbus clients, sockets, TUI.

    (wire/can_codec.py builds python-can Message objects, which open nothing, so `can` is allowed.
    wire/can_net.py is the one transport policy both the CAN driver and the power-source simulator
    apply: keeping udp_multicast on this host needs the socket's TTL and loopback options.)
    """
    devices = ("serial", "pymodbus", "textual", "sqlite3", "socket", "subprocess", "asyncio")
    policy = {("wire.can_net", "socket")}
    bad = []
    for mod, path in MODS.items():
        if not _within(mod, (pkg,)):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and not node.level else [])
            bad += [f"{mod}:{node.lineno} imports {n}" for n in names
                    if n.split(".")[0] in devices and (mod, n.split(".")[0]) not in policy]
    assert not bad, "\n".join(bad)


# Files being split by work merging in this wave; must be empty when the wave lands.
LONG_FILES: dict[str, str] = {}


def test_no_source_file_over_500_lines() -> None:
    sizes = {str(p.relative_to(ROOT)): len(p.read_text(encoding="utf-8").splitlines()) for p in MODS.values()}
    over = {f: n for f, n in sizes.items() if n > MAX_LINES and f not in LONG_FILES}
    assert not over, f"files over {MAX_LINES} lines (split by what they hold): {over}"
    stale = [f for f in LONG_FILES if sizes.get(f, 0) <= MAX_LINES]
    assert not stale, f"no longer over {MAX_LINES} lines: drop from LONG_FILES: {stale}"


def complex_functions() -> list[str]:
    """Every function of ours over MAX_COMPLEXITY (radon: branches, loops, `and`/`or`, comprehensions)."""
    out = []
    for path in MODS.values():
        for block in cc_visit(path.read_text(encoding="utf-8")):
            if block.complexity > MAX_COMPLEXITY:
                out.append(f"{path.relative_to(ROOT)}:{block.lineno} {block.fullname} ({block.complexity})")
    return out


def test_no_function_over_complexity_20() -> None:
    bad = complex_functions()
    assert not bad, f"functions over cyclomatic complexity {MAX_COMPLEXITY} (split them):\n" + "\n".join(bad)


def test_complexity_measure_counts_boolean_operators() -> None:
    """The measure is radon's: `and`/`or` count (ruff's mccabe does not), so a guard chain cannot hide."""
    src = "def f(a, b, c, d):\n    if a and b and c or d:\n        return 1\n    return 0\n"
    assert cc_visit(src)[0].complexity == 5


def test_controller_top_is_small() -> None:
    """At most MAX_TOP_MODULES modules at the top of controller/; the rest live in rooms."""
    top = sorted(p.name for p in (ROOT / "controller").glob("*.py") if p.name != "__init__.py")
    assert len(top) <= MAX_TOP_MODULES, f"controller/ has {len(top)} top-level modules: {top}"


def lazy_imports_without_reason() -> list[str]:
    """Imports inside functions with no comment on their line or just above their block of imports."""
    bad = set()
    for path in MODS.values():
        lines = path.read_text(encoding="utf-8").splitlines()
        for fn in ast.walk(ast.parse("\n".join(lines))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            imports = [n for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))]
            starts = {n.lineno - 1 for n in imports}
            for node in imports:
                j = node.lineno - 1   # walk up over the block of imports to the comment that explains it
                while j >= 0 and "#" not in lines[j] and j in starts:
                    j -= 1
                if j < 0 or "#" not in lines[j]:
                    bad.add(f"{path.relative_to(ROOT)}:{node.lineno} in {fn.name}()")
    return sorted(bad)


def test_imports_inside_functions_say_why() -> None:
    bad = lazy_imports_without_reason()
    assert not bad, "imports inside functions need a comment saying why (start-up time, optional, cycle):\n" + \
        "\n".join(bad)


def literal_attribute_lookups() -> list[str]:
    """`getattr(x, "name")` / `hasattr(x, "name")` in the controller's rooms below its views: a seam
    read by a literal name instead of through a typed port (controller/ports.py). The CLI reads
    argparse namespaces and the TUI duck-types results: those rooms are views, not seams."""
    bad = []
    for mod, path in MODS.items():
        if not mod.startswith("controller.") or room(mod) in ("controller.cli", "controller.tui"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr")
                    and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant) and isinstance(node.args[1].value, str)):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    return bad


def test_no_attribute_read_by_literal_name_in_the_controller() -> None:
    bad = literal_attribute_lookups()
    assert not bad, "read through a typed port instead (docs/architecture.md):\n" + "\n".join(bad)


# Where the runtime meets a device, a link or a result, every parameter and return has a type.
TYPED_SEAMS = ("controller.runtime", "controller.align", "controller.motion", "controller.repair", "controller.api")


def _any_in(ann: ast.expr) -> bool:
    """Does an annotation hide a value behind `Any`? A JSON object (`dict[str, Any]`: a record
    written to the journal or report.json) is a value with a shape, not a seam."""
    if isinstance(ann, ast.Constant) and isinstance(ann.value, str):   # a quoted annotation
        return _any_in(ast.parse(ann.value, mode="eval").body)
    if isinstance(ann, (ast.Name, ast.Attribute)):
        return (ann.id if isinstance(ann, ast.Name) else ann.attr) == "Any"
    if isinstance(ann, ast.Subscript):
        return ast.unparse(ann) != "dict[str, Any]" and (_any_in(ann.value) or _any_in(ann.slice))
    if isinstance(ann, (ast.Tuple, ast.List)):
        return any(_any_in(e) for e in ann.elts)
    if isinstance(ann, ast.BinOp):   # X | Y
        return _any_in(ann.left) or _any_in(ann.right)
    return False


def any_typed_seams(sources: dict[str, str] | None = None) -> list[str]:
    """Every parameter or return annotated `Any` (or a container, callable or future of `Any`) in
    the rooms of TYPED_SEAMS."""
    if sources is None:
        sources = {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8")
                   for m, p in MODS.items() if _within(m, TYPED_SEAMS)}
    bad = []
    for where, text in sources.items():
        for fn in ast.walk(ast.parse(text)):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            a = fn.args
            for arg in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg]:
                if arg is not None and arg.annotation is not None and _any_in(arg.annotation):
                    bad.append(f"{where}:{fn.lineno}: {fn.name}({arg.arg}: {ast.unparse(arg.annotation)})")
            if fn.returns is not None and _any_in(fn.returns):
                bad.append(f"{where}:{fn.lineno}: {fn.name}() -> {ast.unparse(fn.returns)}")
    return bad


def test_no_parameter_typed_any_where_the_runtime_meets_a_device() -> None:
    bad = any_typed_seams()
    assert not bad, "name the type (a port of controller/ports.py, a record, a library's class):\n" + "\n".join(bad)


def test_the_any_rule_sees_what_it_forbids() -> None:
    src = ("from typing import Any\nimport typing\n"
           "def a(x: Any, y: int) -> None: ...\n"
           "async def b(rec: dict[str, Any], f: 'list[Any]') -> typing.Any: ...\n"
           "def c(*args: object, cb: Callable[[int], Any], **kw: Any) -> dict[str, Any]: ...\n")
    assert [b.split(": ", 1)[1] for b in any_typed_seams({"m.py": src})] == [
        "a(x: Any)", "b(f: 'list[Any]')", "b() -> typing.Any", "c(cb: Callable[[int], Any])", "c(kw: Any)"]


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _defined_here(tree: ast.Module) -> set[str]:
    """The names a module defines: its functions, classes and methods, every name it binds
    (assignments, parameters, loop and `with` targets) and the attributes it sets on self/cls."""
    out: set[str] = set()
    for n in ast.walk(tree):
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            out.add(n.name)
        elif isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store):
            out.add(n.id)
        elif isinstance(n, ast.arg):
            out.add(n.arg)
        elif (isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store) and isinstance(n.value, ast.Name)
              and n.value.id in ("self", "cls")):
            out.add(n.attr)
    return out


def private_reads(sources: dict[str, str] | None = None) -> list[str]:
    """Every use of another module's private name in product code (docs/architecture.md, "Packages,
    not friends"): `x._name` where x is not `self`/`cls`, `_name` is defined by another module of
    the product and not by this one; `getattr`/`hasattr`/`setattr(x, "_name")` alike; and
    `from m import _name` of a module of ours. Dunders are not private. A library's internals (no
    module of ours defines the name) are outside the rule."""
    if sources is None:
        sources = {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8")
                   for m, p in MODS.items() if _within(m, PRODUCT)}
    trees = {where: ast.parse(text) for where, text in sources.items()}
    defined = {where: _defined_here(tree) for where, tree in trees.items()}
    bad = []
    for where, tree in trees.items():
        own = defined[where]
        elsewhere = set().union(*(d for w, d in defined.items() if w != where))
        for n in ast.walk(tree):
            if isinstance(n, ast.ImportFrom):
                ours = n.level > 0 or (n.module or "").split(".")[0] in PRODUCT
                bad += [f"{where}:{n.lineno}: from {n.module} import {a.name}" for a in n.names if ours and _is_private(a.name)]
                continue
            if isinstance(n, ast.Attribute):
                obj, name = n.value, n.attr
            elif (isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in ("getattr", "hasattr", "setattr")
                  and len(n.args) >= 2 and isinstance(n.args[1], ast.Constant) and isinstance(n.args[1].value, str)):
                obj, name = n.args[0], n.args[1].value
            else:
                continue
            if (_is_private(name) and name in elsewhere and name not in own
                    and not (isinstance(obj, ast.Name) and obj.id in ("self", "cls"))):
                bad.append(f"{where}:{n.lineno}: {ast.unparse(n)}")
    return bad


def test_no_module_reads_another_modules_private_names() -> None:
    bad = private_reads()
    assert not bad, ("another module's private name (make it public, or share an explicit state object: "
                     "docs/architecture.md):\n" + "\n".join(bad))


def test_the_private_read_rule_sees_what_it_forbids() -> None:
    link = "class Link:\n    def __init__(self):\n        self._pending = []\n        self._port = None\n"
    src = ("from drivers.grbl.link import _helper\nfrom argparse import _SubParsersAction\nclass A:\n"
           "    def __init__(self):\n        self._mine = 1\n"
           "    def f(self, link, other, ser):\n        return (link._pending, other._mine, self._x, link.__dict__,\n"
           "                getattr(link, '_port'), link.public, ser._socket)\n")
    assert [b.split(": ", 1)[1] for b in private_reads({"link.py": link, "x.py": src})] == [
        "from drivers.grbl.link import _helper", "link._pending", "getattr(link, '_port')"]


def test_product_and_docs_cite_no_file_outside_the_repository() -> None:
    """The contract the code relies on is docs/contract.md; nothing of the product or its docs points
    at a folder beside the checkout (tests may read shared parts and firmware sources, and skip)."""
    places = [p for pkg in PRODUCT for p in (ROOT / pkg).rglob("*.py")]
    places += [*(ROOT / "docs").rglob("*.md"), ROOT / "README.md"]
    bad = [f"{p.relative_to(ROOT)}:{i}" for p in places
           for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
           if "../shared" in line or "DESIGN.md" in line]
    assert not bad, "cite docs/contract.md instead: " + ", ".join(bad)


def test_the_architecture_page_names_every_controller_module() -> None:
    """docs/architecture.md names every module of controller/ (by path, or by file name in its room's row)."""
    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    missing = [str(f.relative_to(ROOT)) for f in sorted((ROOT / "controller").rglob("*.py"))
               if f.name != "__init__.py" and str(f.relative_to(ROOT)) not in doc and f"`{f.name}`" not in doc
               and f"{f.parent.name}/{f.name}" not in doc]
    assert not missing, "name these in docs/architecture.md: " + ", ".join(missing)


TEST_ROOMS = frozenset({"core", "wire", "planner", "drivers", "sims", "job", "journal", "report", "records", "motion",
                        "align", "export", "runtime", "opcua", "repair", "tui", "cli"})


def test_tests_live_in_folders_by_room() -> None:
    """tests/<room>/ mirrors the code (docs/testing.md): no test file at the top but this one, and
    every folder of tests is a room (a layer, or a room of controller/)."""
    top = sorted(p.name for p in (ROOT / "tests").glob("test_*.py") if p.name != Path(__file__).name)
    assert not top, "move these into tests/<room>/: " + ", ".join(top)
    folders = {p.parent.relative_to(ROOT / "tests").parts[0] for p in (ROOT / "tests").rglob("test_*.py")
               if p.parent != ROOT / "tests"}
    assert folders <= TEST_ROOMS, f"not a room: {sorted(folders - TEST_ROOMS)}"
    cross = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests").rglob("*.py")
                   if re.search(r"^\s*from tests\.(\w+\.)*test_\w+ import", p.read_text(encoding="utf-8"), re.M))
    assert not cross, "a test imports another test module; move the helper beside conftest: " + ", ".join(cross)
