"""The import structure of the project's packages, checked statically.

Builds the import graph of ``hmpf``, ``indexer`` and ``service`` by parsing every
module with :mod:`ast` (nothing is imported), and asserts:

(a) no import circle among modules, counting the imports that run when a module is
    loaded (module level, ``if TYPE_CHECKING:`` blocks excluded);
(b) the layering ``hmpf`` < ``indexer`` < ``service``: the core never imports the
    indexer or the service, the indexer never imports the service (an "upward arrow"),
    counting every import, inside functions and type-checking blocks too;
(c) an import inside a function is either of an optional heavy third-party
    dependency (``OPTIONAL_HEAVY``) or listed in ``ALLOWED_IN_FUNCTION`` with the
    reason it cannot be at module level.

Run it with ``-s`` to see what it finds.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("hmpf", "indexer", "service")
# Lower index = lower layer; a module may import only its own layer or lower ones.
LAYER = {"hmpf": 0, "indexer": 1, "service": 2}

# Third-party dependencies that are optional extras or too heavy for the serving
# path / the CLI's start-up: importing them inside the function that needs them is
# the intended pattern (the module stays importable without them).
OPTIONAL_HEAVY = frozenset(
    {
        "torch",  # the CNN backbones' training-time runtime; serving runs ONNX
        "torchvision",
        "onnx",  # export / model surgery only
        "onnxruntime",  # the CNN runtime; not installed for classical methods
        "openvino",  # the openvino CNN runtimes (an extra of their own)
        "ray",  # distributed indexing extra
        "faiss",  # ANN extra
        "matplotlib",  # figures only
        "playwright",  # browser tests only
        "h5py",  # MATLAB v7.3 model files only
        "scipy",  # MATLAB v5 model files / geometric checks only
        "cv2",  # OpenCV: KAZE and image decoding extras
        "uvicorn",  # running the server, not building the app
        "fastapi",  # the service's framework, imported only when serving
        "httpx",  # HTTP client transport, optional
        "tqdm",  # progress bars, optional
        "threadpoolctl",  # BLAS thread limits, optional
        "yaml",  # config files only
        "efficientnet_lite_pytorch",  # EfficientNet's torch model code (hmpf[cnn])
    }
)

# Command modules: a command loads numpy, OpenCV and the evaluation inside its body (``run``),
# so that --help and --version are instant and Ctrl-C while they load is one line and exit
# 130 (tests/hmpf/test_cli_common.py); their in-project imports inside functions are that.
COMMAND_MODULES: dict[str, str] = {
    "hmpf.cli.args": "argument helpers of the evaluation commands, called inside run",
    "hmpf.cli.calibrate": "hmpf-calibrate",
    "hmpf.cli.eval": "hmpf-eval",
    "hmpf.cli.experiments": "hmpf-eval experiments",
    "hmpf.cli.replay": "hmpf-replay",
    "indexer.cli": "hmpf-index",
    "service.cli": "hmpf-serve",
}

# Other imports inside functions that are allowed, each with the reason (empty: every one
# that hid a circle or had no reason was moved to module level). Keys: (importing module,
# imported module).
ALLOWED_IN_FUNCTION: dict[tuple[str, str], str] = {}

# Module-level import circles still present, each with a reason; to remove.
# Keys: frozenset of the modules in the strongly connected component.
ALLOWED_CYCLES: dict[frozenset[str], str] = {}


@dataclass(frozen=True)
class Edge:
    src: str
    dst: str  # absolute module name (in-project: resolved to a module/package)
    line: int
    in_function: bool
    type_checking: bool


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _all_modules() -> dict[str, Path]:
    mods: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            mods[_module_name(path)] = path
    return mods


def _is_type_checking(test: ast.expr) -> bool:
    if isinstance(test, ast.Name):
        return test.id == "TYPE_CHECKING"
    if isinstance(test, ast.Attribute):
        return test.attr == "TYPE_CHECKING"
    return False


def _resolve_relative(module: str, is_package: bool, level: int, name: str | None) -> str:
    parts = module.split(".")
    if not is_package:
        parts = parts[:-1]
    if level > 1:
        parts = parts[: len(parts) - (level - 1)]
    base = ".".join(parts)
    if name:
        return f"{base}.{name}" if base else name
    return base


def _edges_of(module: str, path: Path, modules: dict[str, Path]) -> list[Edge]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    is_package = path.name == "__init__.py"
    edges: list[Edge] = []

    def visit(node: ast.AST, in_function: bool, type_checking: bool) -> None:
        if isinstance(node, ast.Import):
            for alias in node.names:
                edges.append(Edge(module, alias.name, node.lineno, in_function, type_checking))
            return
        if isinstance(node, ast.ImportFrom):
            if node.level:
                target = _resolve_relative(module, is_package, node.level, node.module)
            else:
                target = node.module or ""
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                dst = sub if sub in modules else target
                edges.append(Edge(module, dst, node.lineno, in_function, type_checking))
            return
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            in_function = True
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                visit(child, in_function, True)
            for child in node.orelse:
                visit(child, in_function, type_checking)
            return
        for child in ast.iter_child_nodes(node):
            visit(child, in_function, type_checking)

    visit(tree, False, False)
    return edges


def _in_project(name: str) -> bool:
    return name.split(".")[0] in PACKAGES


def _project_target(name: str, modules: dict[str, Path]) -> str:
    """The in-project module an absolute name refers to (longest existing prefix)."""
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in modules:
            return cand
        parts.pop()
    return name


def build_graph() -> tuple[dict[str, Path], list[Edge]]:
    modules = _all_modules()
    edges: list[Edge] = []
    for mod, path in modules.items():
        for e in _edges_of(mod, path, modules):
            if _in_project(e.dst):
                e = Edge(
                    e.src, _project_target(e.dst, modules), e.line, e.in_function, e.type_checking
                )
            edges.append(e)
    return modules, list(dict.fromkeys(edges))


def strongly_connected(nodes: list[str], succ: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm, iterative."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(sorted(succ.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            advanced = False
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(succ.get(w, ())))))
                    advanced = True
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                out.append(sorted(comp))
    return out


def find_cycles(include_functions: bool = False) -> list[list[str]]:
    """Circles at module level; with ``include_functions``, also those that imports
    inside functions hide (they break at run time only by being deferred)."""
    modules, edges = build_graph()
    succ: dict[str, set[str]] = {m: set() for m in modules}
    for e in edges:
        if e.type_checking or e.dst not in modules or e.dst == e.src:
            continue
        if e.in_function and not include_functions:
            continue
        succ[e.src].add(e.dst)
    comps = strongly_connected(sorted(modules), succ)
    return sorted(c for c in comps if len(c) > 1)


def find_upward() -> list[Edge]:
    _, edges = build_graph()
    out = []
    for e in edges:
        if not _in_project(e.dst):
            continue
        if LAYER[e.dst.split(".")[0]] > LAYER[e.src.split(".")[0]]:
            out.append(e)
    return out


def find_in_function() -> tuple[list[Edge], list[Edge]]:
    """(allowed, disallowed) imports inside functions."""
    _, edges = build_graph()
    ok, bad = [], []
    for e in edges:
        if not e.in_function:
            continue
        top = e.dst.split(".")[0]
        if (
            top in OPTIONAL_HEAVY
            or (e.src, e.dst) in ALLOWED_IN_FUNCTION
            or (e.src in COMMAND_MODULES and _in_project(e.dst))
        ):
            ok.append(e)
        else:
            bad.append(e)
    return ok, bad


def _fmt(e: Edge) -> str:
    return f"{e.src}:{e.line} -> {e.dst}"


def _allowed_tag(cycle: list[str]) -> str:
    reason = ALLOWED_CYCLES.get(frozenset(cycle))
    return f" (allowed: {reason})" if reason else ""


def test_no_import_cycles() -> None:
    cycles = find_cycles()
    print(f"\n{len(cycles)} import circle(s) at module level")
    for c in cycles:
        print("  circle:", " <-> ".join(c) + _allowed_tag(c))
    assert [c for c in cycles if frozenset(c) not in ALLOWED_CYCLES] == []


def test_no_circles_hidden_by_imports_in_functions() -> None:
    cycles = find_cycles(include_functions=True)
    print(f"\n{len(cycles)} import circle(s) counting imports inside functions")
    for c in cycles:
        print("  circle:", " <-> ".join(c) + _allowed_tag(c))
    assert [c for c in cycles if frozenset(c) not in ALLOWED_CYCLES] == []


def test_no_upward_imports() -> None:
    up = find_upward()
    print(f"\n{len(up)} upward import(s)")
    for e in up:
        print("  up:", _fmt(e))
    assert up == []


def test_imports_in_functions_only_for_optional_heavy_dependencies() -> None:
    ok, bad = find_in_function()
    print(f"\n{len(ok) + len(bad)} import(s) inside functions: {len(ok)} allowed, {len(bad)} not")
    for e in bad:
        print("  in function:", _fmt(e))
    assert bad == []


def _has_reason(lines: list[str], line: int) -> bool:
    """A comment on the import's line, or on the comment lines right above it (a block of
    imports may share the comment above its first line)."""
    i = line - 1
    if "#" in lines[i]:
        return True
    while i > 0 and lines[i - 1].lstrip().startswith(("import ", "from ")):
        i -= 1
    return i > 0 and lines[i - 1].lstrip().startswith("#")


def test_imports_in_functions_say_why() -> None:
    """Each import of an optional or heavy dependency inside a function has a comment saying
    why it is there (a command module's are explained once, in ``COMMAND_MODULES``)."""
    modules, _ = build_graph()
    ok, _ = find_in_function()
    silent = []
    for e in ok:
        if e.src in COMMAND_MODULES and _in_project(e.dst):
            continue
        lines = modules[e.src].read_text(encoding="utf-8").splitlines()
        if not _has_reason(lines, e.line):
            silent.append(_fmt(e))
    print(f"\n{len(ok)} import(s) inside functions, {len(silent)} without a reason")
    assert silent == []


def test_allow_lists_are_not_stale() -> None:
    _, edges = build_graph()
    present = {(e.src, e.dst) for e in edges if e.in_function}
    assert [k for k in ALLOWED_IN_FUNCTION if k not in present] == []
    cycles = {frozenset(c) for c in find_cycles(include_functions=True)}
    assert [sorted(k) for k in ALLOWED_CYCLES if k not in cycles] == []


def test_checker_sees_a_known_relative_import() -> None:
    # Guard against the checker silently seeing nothing.
    modules, edges = build_graph()
    assert len(modules) > 50
    assert any(e.src == "hmpf.client" for e in edges)


if __name__ == "__main__":  # pragma: no cover - manual use
    for c in find_cycles():
        print("circle:", c)
    for c in find_cycles(include_functions=True):
        print("hidden circle:", c)
    for e in find_upward():
        print("up:", _fmt(e))
    for e in find_in_function()[1]:
        print("in function:", _fmt(e))
    sys.exit(0)
