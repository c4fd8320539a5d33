"""The module graph keeps the architecture's layers, so a reader can follow it and each role installs
and starts on its own (docs/architecture.md draws them):

    common  <-  onboard | edge | sim  <-  plan  <-  experiment, reports, observers, bench  <-  cli

- `common` imports no component; `onboard`, `edge` and `sim` import none of each other (what two
  components share lives in `common`; the simulator is handed to the drone by whoever starts both);
- the components import nothing of the plan, experiment, reports, observers, bench or CLI, and those
  import no CLI;
- a flight is data (`plan`: the scenario, its faults, what a flight recorded), which imports nothing
  that flies or reports; the reports read a Recording and its plan and import nothing of the
  experiment, which flies (the experiment uses the reports to write them);
- the pure modules (the logic the I/O shells call, tested on an injected clock) import no I/O: none of
  zenoh, pymavlink, cv2, aiohttp, asyncio, threading or time, and nothing that brings in the first five;
- no module imports itself back, function-level imports included.

An AST walk over the source folders rather than import-linter: setuptools' `package-dir` maps `common/`,
`onboard/`, ... into `dynqos.*`, which import-linter's graph builder (grimp) cannot follow from the
source tree, and the rule on third-party I/O libraries needs each module's own imports, which this walk
has at hand. Each rule is checked to fail on a graph with one forbidden import put back.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = {
    "dynqos": "dynqos",
    "dynqos.common": "common",
    "dynqos.onboard": "onboard",
    "dynqos.edge": "edge",
    "dynqos.sim": "sim",
    "dynqos.bench": "bench",
}
COMPONENTS = ("dynqos.onboard", "dynqos.edge", "dynqos.sim")
ABOVE = ("dynqos.experiment", "dynqos.reports", "dynqos.observers", "dynqos.bench")
PLAN = "dynqos.plan"
CLI = "dynqos.cli"
PURE = (
    "dynqos.onboard.supervisor",
    "dynqos.onboard.supervisor_status",
    "dynqos.onboard.core",
    "dynqos.onboard.pid",
    "dynqos.onboard.takeoff",
    "dynqos.edge.mpc.problem",
    "dynqos.edge.qos.arbiter",
    "dynqos.edge.qos.grants",
    "dynqos.edge.operator.profile_fit",
    "dynqos.edge.replicas",
    "dynqos.edge.ros2.codec",
    "dynqos.edge.ros2.translate",
    "dynqos.edge.ros2.wire",
    "dynqos.onboard.frame_time",
    "dynqos.onboard.clock_offset",
    "dynqos.sim.network.scheduler",
    "dynqos.sim.network.cell_core",
    "dynqos.sim.vehicle.dynamics",
)
IO = ("zenoh", "pymavlink", "cv2", "aiohttp", "asyncio")  # not even through another module
IO_DIRECT = (*IO, "threading", "time")  # not in the pure module itself

Graph = dict[str, set[str]]


def _modules() -> dict[str, Path]:
    found = {}
    mapped = {ROOT / folder for folder in PACKAGES.values()}
    for package, folder in PACKAGES.items():
        base = ROOT / folder
        for path in base.rglob("*.py"):
            inner = path.relative_to(base).with_suffix("").parts
            if any(p.parent in mapped and p.parent != base for p in path.parents if p != path):
                continue  # a mapped folder inside another (never so far): counted under its own name
            parts = inner[:-1] if inner[-1] == "__init__" else inner
            found[".".join((package, *parts))] = path
    return found


def _runtime_nodes(tree: ast.AST) -> list[ast.AST]:
    """Every node but those under `if TYPE_CHECKING:` (imports for annotations only, never run)."""
    out: list[ast.AST] = []
    todo = [tree]
    while todo:
        node = todo.pop()
        out.append(node)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            todo.extend(node.orelse)
            continue
        todo.extend(ast.iter_child_nodes(node))
    return out


def _imports(path: Path, modules: set[str]) -> tuple[set[str], set[str]]:
    """Everything a module imports (dotted names; for `from m import x` the module m.x when it is one,
    else m), and the top-level names of those imports."""
    names: set[str] = set()
    for node in _runtime_nodes(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                inner = f"{node.module}.{alias.name}"
                names.add(inner if inner in modules else node.module)
        elif isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
    return names, {n.split(".")[0] for n in names}


def graphs() -> tuple[Graph, Graph]:
    """The dynqos import graph and each module's third-party (and standard-library) top-level imports."""
    modules = _modules()
    graph: Graph = {}
    external: Graph = {}
    for name, path in modules.items():
        names, tops = _imports(path, set(modules))
        graph[name] = {n for n in names if n in modules and n != name}
        external[name] = tops - {"dynqos"}
    return graph, external


def import_graph() -> Graph:
    return graphs()[0]


def _in(module: str, packages: tuple[str, ...] | str) -> bool:
    packages = (packages,) if isinstance(packages, str) else packages
    return any(module == p or module.startswith(p + ".") for p in packages)


def _component(module: str) -> str | None:
    return next((c for c in COMPONENTS if _in(module, c)), None)


def layer_breaches(graph: Graph) -> set[tuple[str, str]]:
    """Every import that points up the layers or across between components."""
    out = set()
    for module, targets in graph.items():
        for target in targets:
            if _in(module, "dynqos.common") and not _in(target, "dynqos.common"):
                out.add((module, target))
            elif _component(module) and not (_in(target, "dynqos.common") or _in(target, "dynqos._version")):
                if _component(target) != _component(module):
                    out.add((module, target))
            elif (
                (_in(module, ABOVE) and _in(target, CLI))
                or (_in(module, PLAN) and _in(target, (*ABOVE, CLI)))
                or (_in(module, "dynqos.reports") and _in(target, "dynqos.experiment"))
            ):
                out.add((module, target))
    return out


def _closure(graph: Graph, start: str) -> set[str]:
    seen, todo = {start}, [start]
    while todo:
        for target in graph.get(todo.pop(), ()):
            if target not in seen:
                seen.add(target)
                todo.append(target)
    return seen


def impure(graph: Graph, external: Graph, pure: tuple[str, ...] = PURE) -> dict[str, set[str]]:
    """What I/O each pure module imports, itself (IO_DIRECT) or through any module it imports (IO)."""
    out = {}
    for module in pure:
        if module not in graph:
            continue
        found = external[module] & set(IO_DIRECT)
        for reached in _closure(graph, module) - {module}:
            found |= {f"{lib} (through {reached})" for lib in external[reached] & set(IO)}
        if found:
            out[module] = found
    return out


def cycles(graph: Graph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


# ---- the checks on the tree -------------------------------------------------------------------------------


def test_the_walk_finds_every_module_under_its_import_name() -> None:
    graph = import_graph()
    assert len(graph) > 100
    for name in ("dynqos.cli", "dynqos.edge.qos.agent", "dynqos.sim.vehicle.mavlink", "dynqos.common.keys"):
        assert name in graph


def test_no_module_imports_itself_back() -> None:
    assert cycles(import_graph()) == []


def test_the_layers_hold() -> None:
    assert layer_breaches(import_graph()) == set()


def test_pure_modules_import_no_io() -> None:
    graph, external = graphs()
    assert {m for m in PURE if m in graph} >= {"dynqos.onboard.supervisor", "dynqos.edge.qos.grants"}
    assert impure(graph, external) == {}


def test_the_benchmarks_use_the_runner_not_the_demo() -> None:
    graph = import_graph()
    demo = "dynqos.experiment.demo"
    assert {m for m, targets in graph.items() if _in(m, "dynqos.bench") and demo in targets} == set()


# ---- each rule fails when one forbidden import is put back ----------------------------------------------


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_each_forbidden_direction_is_caught() -> None:
    graph = import_graph()
    for module, target in [
        ("dynqos.edge.operator.client", "dynqos.sim.network.operator_schema"),  # edge -> sim (the old defect)
        ("dynqos.onboard.camera", "dynqos.sim.vehicle.render"),  # onboard -> sim
        ("dynqos.sim.network.cell", "dynqos.edge.qos.grants"),  # sim -> edge
        ("dynqos.common.config", "dynqos.onboard.pid"),  # common -> a component
        ("dynqos.onboard.daemon", "dynqos.plan.scenario"),  # a component -> the experiment
        ("dynqos.reports.summary", "dynqos.cli"),  # reports -> the CLI
        ("dynqos.reports.summary", "dynqos.experiment.faults"),  # reports -> what flies (the old circle)
        ("dynqos.plan.scenario", "dynqos.experiment.runner"),  # the plan -> what flies
        ("dynqos.plan.recording", "dynqos.reports.machine"),  # the plan -> the reports
    ]:
        mutated = {m: set(t) for m, t in graph.items()}
        mutated[module].add(target)
        assert layer_breaches(mutated) == {(module, target)}


def test_io_in_a_pure_module_is_caught_directly_and_through_another() -> None:
    graph, external = graphs()
    direct = {m: set(t) for m, t in external.items()}
    direct["dynqos.onboard.supervisor"].add("time")
    assert impure(graph, direct) == {"dynqos.onboard.supervisor": {"time"}}
    through = {m: set(t) for m, t in graph.items()}
    through["dynqos.edge.qos.grants"].add("dynqos.common.transport")  # opens zenoh sessions
    assert impure(through, external) == {
        "dynqos.edge.qos.grants": {"zenoh (through dynqos.common.transport)"}
    }


# ---- sizes a reader takes in at once ---------------------------------------------------------------------

MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80
MAX_CLI_MODULE_LINES = 250


def _sources() -> list[Path]:
    return sorted(p for folder in PACKAGES.values() for p in (ROOT / folder).rglob("*.py"))


def oversized(paths: list[Path], root: Path = ROOT) -> list[str]:
    """Modules and functions past their limits, and any `noqa` that silences a length or complexity
    rule instead of a shorter function."""
    found = []
    for path in paths:
        text = path.read_text(encoding="utf-8")
        name = str(path.relative_to(root))
        lines = text.count("\n")
        limit = MAX_CLI_MODULE_LINES if name.startswith("dynqos/cli/") else MAX_MODULE_LINES
        if lines > limit:
            found.append(f"{name}: {lines} lines (at most {limit})")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    found.append(f"{name}:{node.lineno} {node.name}: {length} lines")
        for number, line in enumerate(text.splitlines(), 1):
            if "noqa" in line and any(rule in line for rule in ("C901", "PLR0915", "E501")):
                found.append(f"{name}:{number}: a noqa for length or complexity")
    return found


def test_no_module_or_function_is_longer_than_a_reader_takes_in() -> None:
    assert oversized(_sources()) == []


def test_the_size_check_finds_a_long_module_a_long_function_and_a_silenced_rule(tmp_path: Path) -> None:
    long_module = tmp_path / "long.py"
    long_module.write_text("x = 1\n" * (MAX_MODULE_LINES + 1))
    long_function = tmp_path / "function.py"
    long_function.write_text("def f() -> None:\n" + "    pass\n" * MAX_FUNCTION_LINES)
    silenced = tmp_path / "silenced.py"
    silenced.write_text("def g() -> None:  # noqa: C901\n    pass\n")
    found = oversized([long_module, long_function, silenced], root=tmp_path)
    assert [line.split(":")[0] for line in found] == ["long.py", "function.py", "silenced.py"]


def test_the_command_line_starts_without_the_components_it_does_not_run() -> None:
    """Every process starts through the CLI: a restarted MPC must not first import the simulator (its
    MAVLink dialect alone is 0.3 s), nor any service load what only another command needs."""
    import subprocess
    import sys

    code = (
        "import sys, dynqos.cli; "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('pymavlink', 'osqp', 'cv2', 'zenoh', "
        "'aiohttp', 'matplotlib') or m.startswith(('dynqos.sim.', 'dynqos.edge.', 'dynqos.onboard.'))))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True
    )
    assert loaded.stdout.strip() == "['dynqos.sim.vehicle']", loaded.stdout  # the package: MAX_INSTANCE


# Files where a `# fmt: skip` keeps a table whose alignment carries meaning (none today): everywhere else
# the formatter lays the code out.
ALIGNED_TABLES: frozenset[str] = frozenset()


def test_the_formatter_lays_out_the_source() -> None:
    skipped = [
        f"{path.relative_to(ROOT)}:{number}"
        for path in _sources()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if "# fmt: skip" in line and str(path.relative_to(ROOT)) not in ALIGNED_TABLES
    ]
    assert skipped == []


def event_loops_started(source: str) -> int:
    """How many times a module starts an event loop (`asyncio.run(...)` calls, by the syntax tree)."""
    return sum(
        1
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "run"
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id == "asyncio"
    )


def test_only_the_edge_runtime_starts_an_event_loop() -> None:
    """One event loop per edge process, the runtime's (edge/runtime.py): a service that started its own
    would open a second operator client session and hand state between loops (the fleet planner did)."""
    started = {
        str(path.relative_to(ROOT)): n
        for path in (ROOT / "edge").rglob("*.py")
        if (n := event_loops_started(path.read_text(encoding="utf-8")))
    }
    assert started == {"edge/runtime.py": 1}
    assert event_loops_started("import asyncio\nasyncio.run(a())\nasyncio.run(b())\n") == 2


# The edge's own zenoh router is zenoh's router itself, not a service on a session: it has no core.
ZENOH_SESSIONS = ("dynqos.edge.runtime", "dynqos.edge.router")


def zenoh_reached(graph: Graph, external: Graph) -> set[str]:
    """The edge modules that import zenoh or open a session (common/transport.py) themselves."""
    return {
        m
        for m in graph
        if _in(m, "dynqos.edge")
        and m not in ZENOH_SESSIONS
        and ("zenoh" in external[m] or "dynqos.common.transport" in graph[m])
    }


def test_edge_services_reach_zenoh_only_through_the_runtime() -> None:
    """Each service gets its bus from the runtime, which opens the session; none imports zenoh or the
    transport. Each service in `dynqos edge` is a core the runtime drives."""
    graph, external = graphs()
    assert zenoh_reached(graph, external) == set()
    assert zenoh_reached({"dynqos.edge.x": {"dynqos.common.transport"}}, {"dynqos.edge.x": set()}) == {
        "dynqos.edge.x"
    }
    assert zenoh_reached({"dynqos.edge.y": set()}, {"dynqos.edge.y": {"zenoh"}}) == {"dynqos.edge.y"}
    from dynqos.cli.edge_cmd import SERVICES
    from dynqos.edge.runtime import EdgeCore

    for name, (module_name, _help) in SERVICES.items():
        if module_name in ZENOH_SESSIONS:
            continue
        module = importlib.import_module(module_name)
        cores = [c for c in vars(module).values() if isinstance(c, type) and issubclass(c, EdgeCore)]
        assert any(c.__module__ == module_name for c in cores), f"{name}: no EdgeCore in {module_name}"
        assert "dynqos.edge.runtime" in graph[module_name], f"{name} does not run on the runtime"
