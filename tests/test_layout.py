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
