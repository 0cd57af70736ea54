"""The package's shape: kernels import nothing else from it; production code never imports the evaluation."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"


def _imports(path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            yield node.level, node.module or "", [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield 0, a.name, []


def test_kernels_import_nothing_else_from_the_package():
    for path in (PACKAGE / "kernels").glob("*.py"):
        for level, module, names in _imports(path):
            assert not module.startswith("pipeline"), (path.name, module)
            assert level <= 1, (path.name, module)      # "from . import x" stays inside kernels


def test_production_code_never_imports_the_evaluation():
    # the CLI's `evaluate` command is the one door (imported only when that command runs)
    for path in PACKAGE.rglob("*.py"):
        if path.name in ("evaluate.py", "cli.py"):
            continue
        for _, module, names in _imports(path):
            assert "evaluate" not in module and "evaluate" not in names, (path, module, names)


def test_the_evaluation_lives_beside_the_other_dask_graphs():
    assert (PACKAGE / "orchestrate" / "evaluate.py").is_file() and not (PACKAGE / "evaluate.py").exists()


def _module_name(path):
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _package_imports():
    """{module: [(imported module, [names])]} of every import in the package, function-level ones included."""
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        out = []
        for level, module, names in _imports(path):
            if level:
                base = package.split(".")[: len(package.split(".")) - (level - 1)]
                module = ".".join(base + ([module] if module else []))
            if not module.startswith("pipeline"):
                continue
            for n in names or [""]:            # "from . import x" may import a submodule x
                target = f"{module}.{n}" if n and f"{module}.{n}" in modules else module
                out.append((target, n))
        graph[name] = out
    return modules, graph


def test_no_import_cycle_in_the_package():
    modules, graph = _package_imports()
    edges = {m: {t for t, _ in graph[m] if t in modules and t != m and not m.startswith(t + ".")} for m in graph}
    state, stack = {}, []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(t):] + [t]))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = "done"

    for m in sorted(edges):
        if m not in state:
            visit(m)


def test_no_module_imports_another_modules_private_names():
    _, graph = _package_imports()
    private = [(m, t, n) for m, imports in graph.items() for t, n in imports
               if n.startswith("_") and not n.startswith("__")]
    assert not private, private
