"""The package's shape, read from its source with ``ast`` alone (nothing is imported): layers that point one way,
and short pieces.

**Layers.** Every module of ``freeform/`` belongs to one layer of :data:`LAYERS` (the most specific prefix names
it); a module may import modules of its own layer or of a lower one, never of a higher one, and the module import
graph has no cycle. Every import statement counts: at module level, inside a function (an import done late to dodge
a circle is still an arrow), under ``TYPE_CHECKING``. ``from freeform.x import y`` is an arrow to ``freeform.x.y``
where that is a module, else to ``freeform.x``. The implicit import of a parent package (importing
``freeform.sim.config`` runs ``freeform/sim/__init__.py``) is not an arrow: a package's ``__init__`` re-exports
its own modules.

**Short pieces.** No function of ``freeform/`` over :data:`MAX_FUNCTION_LINES` lines (from its ``def`` to its last
line, docstring and blank lines included), none with more than :data:`MAX_PARAMETERS` parameters (``self``/``cls``
not counted; ``*args``/``**kwargs`` counted), no module over :data:`MAX_MODULE_LINES` lines. A nested function
(a Taichi kernel factory's kernels and funcs, a local helper) is measured as its own function, and its lines do
not count for the function that encloses it; what remains of the enclosing function must itself be short.
Functions decorated ``@ti.func`` or ``@ti.kernel`` are exempt from the parameter rule only: a Taichi func is
inlined and takes the values its caller holds in registers — bundling them (a struct, a vector) or re-reading them
inside would cost instructions in the hottest loop, which ``scripts/profile_sim.py`` counts per voxel-step — and a
kernel's arguments are the ndarrays and scalars Taichi launches it with.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "freeform"
MAX_FUNCTION_LINES = 60
MAX_PARAMETERS = 8
MAX_MODULE_LINES = 600
LONG_MODULES: set[str] = set()  # (modules allowed past MAX_MODULE_LINES, each with its reason: none today)
TAICHI_DECORATORS = ("func", "kernel")

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    # what everything may use: files and checkpoints, records, the logger, argument checks, action distributions
    ("foundation", ("freeform", "freeform._conf_dir", "freeform.validation", "freeform.files", "freeform.checkpoint",
                    "freeform.records", "freeform.logger", "freeform.preemption", "freeform.distributions",
                    "freeform.tables")),
    ("sim", ("freeform.sim",)),  # grids and actuation in, states and displacements out; knows nothing of RL
    ("body", ("freeform.body", "freeform.surface", "freeform.mesh", "freeform.io")),  # bodies, metrics, files
    ("render", ("freeform.render",)),  # images and videos of grids and recordings
    ("envs", ("freeform.envs",)),  # VecEnvs and tasks: join the body and the simulation through a reward
    ("learner", ("freeform.learner",)),  # the protocol every trainer-driven algorithm implements
    ("networks", ("freeform.agents.networks",)),  # the paper's actor-critic, the controllers, heads, trunks, cores
    ("collectives", ("freeform.agents.distributed",)),  # the one place for distributed collectives
    ("ppo", ("freeform.agents.ppo",)),  # PPO over any VecEnv: nothing of voxels in the algorithm
    ("distill", ("freeform.agents.distill",)),  # teachers as one bank, DAgger into a student, priors
    ("agents", ("freeform.agents",)),  # the controller file, and the package's names
    ("zoo", ("freeform.zoo",)),  # the trained controllers that ship in the wheel
    ("evolve", ("freeform.evolve",)),  # the evolutionary learners over the design space
    ("config", ("freeform.config",)),  # the run's typed config, every section's dataclass
    ("run", ("freeform.run", "freeform.train", "freeform.launch", "freeform.render_cli",
             "freeform.control")),  # the applications
)
"""Lowest first: data flows from ``run`` down (``docs/architecture.md``)."""


def modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name)."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        found[".".join(parts)] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The freeform modules that module ``name`` (at ``path``) imports, by every import statement in it."""

    def module_of(dotted: str) -> str | None:
        while dotted and dotted not in known:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str | None] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(module_of(a.name) for a in node.names if a.name.split(".")[0] == "freeform")
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, level - 1 packages up
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            if base.split(".")[0] != "freeform":
                continue
            found.update(f"{base}.{a.name}" if f"{base}.{a.name}" in known else module_of(base) for a in node.names)
    found.discard(None)
    found.discard(name)
    return found  # type: ignore[return-value]


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def layer(name: str) -> int:
    """The index in :data:`LAYERS` of module ``name``: its most specific prefix's."""
    best, index = -1, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            fits = name == prefix or (prefix != "freeform" and name.startswith(prefix + "."))
            if fits and len(prefix) > best:
                best, index = len(prefix), i
    return index


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_every_module_has_a_layer() -> None:
    assert [name for name in modules() if layer(name) < 0] == []


def test_no_module_imports_a_higher_layer() -> None:
    upward = [f"{name} ({LAYERS[layer(name)][0]}) -> {target} ({LAYERS[layer(target)][0]})"
              for name, targets in sorted(graph().items()) for target in sorted(targets) if layer(target) > layer(name)]
    assert upward == []


def test_the_import_graph_has_no_cycle() -> None:
    assert cycles(graph()) == []


def test_the_checks_see_a_circle_and_an_arrow_up(tmp_path: Path) -> None:
    """The checks themselves: a planted circle is found, and an arrow from sim up to the agents is one."""
    edges = {"freeform.a": {"freeform.b"}, "freeform.b": {"freeform.c"}, "freeform.c": {"freeform.a"},
             "freeform.d": {"freeform.a"}}
    assert cycles(edges) == [["freeform.a", "freeform.b", "freeform.c"]]
    assert layer("freeform.sim.engine") < layer("freeform.agents.ppo.ppo") < layer("freeform.run.build")
    assert layer("freeform") == 0 and layer("freeform.distributions") == 0
    known = {"freeform.sim": Path("x"), "freeform.sim.config": Path("y"), "freeform.agents": Path("z")}
    source = "def f():\n    from freeform.agents import PPO\n    from .config import SimConfig\n"
    planted = tmp_path / "planted.py"
    planted.write_text(source)
    assert imports("freeform.sim.planted", planted, known) == {"freeform.agents", "freeform.sim.config"}


FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef)


def functions() -> list[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """Every function of the package, nested ones included: ``(path:line name, node)``."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, FUNCTIONS):
                found.append((f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name}", node))
    return found


def own_lines(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """The lines from ``def`` to the function's end, less those of the functions nested in it (with their
    decorators)."""
    lines = set(range(function.lineno, function.end_lineno + 1))  # type: ignore[operator]
    for node in ast.walk(function):
        if node is not function and isinstance(node, FUNCTIONS):
            start = min([d.lineno for d in node.decorator_list] + [node.lineno])
            lines -= set(range(start, node.end_lineno + 1))  # type: ignore[operator]
    return len(lines)


def parameters(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    a = function.args
    names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)] + [p.arg for p in (a.vararg, a.kwarg) if p]
    return len([n for n in names if n not in ("self", "cls")])


def is_taichi(function: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any(isinstance(d, ast.Attribute) and d.attr in TAICHI_DECORATORS and getattr(d.value, "id", "") == "ti"
               for d in function.decorator_list)


def test_no_function_is_long() -> None:
    long = {name: n for name, f in functions() if (n := own_lines(f)) > MAX_FUNCTION_LINES}
    assert long == {}


def test_no_function_takes_many_parameters() -> None:
    many = {name: n for name, f in functions() if (n := parameters(f)) > MAX_PARAMETERS and not is_taichi(f)}
    assert many == {}


def test_no_module_is_long() -> None:
    lengths = {str(p.relative_to(PACKAGE)): len(p.read_text().splitlines()) for p in PACKAGE.rglob("*.py")}
    assert {name: n for name, n in lengths.items() if n > MAX_MODULE_LINES and name not in LONG_MODULES} == {}
    assert all(name in lengths for name in LONG_MODULES)  # (an exception outlives its module: remove it)


def test_the_size_rules_measure_what_they_say() -> None:
    """A nested function's lines count for itself, not its factory; parameters skip self; Taichi funcs are seen."""
    source = ("def factory(a, b):\n"
              "    x = 1\n"
              "    @ti.func\n"
              "    def inner(self, c, d, e):\n"
              "        return c\n"
              "    return inner\n")
    factory, inner = [n for n in ast.walk(ast.parse(source)) if isinstance(n, FUNCTIONS)]
    assert (own_lines(factory), own_lines(inner)) == (3, 2)
    assert (parameters(factory), parameters(inner)) == (2, 3)
    assert (is_taichi(factory), is_taichi(inner)) == (False, True)
