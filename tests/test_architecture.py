"""Architecture rules that are cheap to check mechanically (README "Architecture")."""

import ast
from pathlib import Path

APP = Path(__file__).resolve().parents[1] / "app"
MAX_FUNCTION_LINES = 120


def _functions(path: Path):
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def test_no_function_over_120_lines():
    long = []
    for path in sorted(APP.rglob("*.py")):
        rel = path.relative_to(APP).as_posix()
        for fn in _functions(path):
            n = fn.end_lineno - fn.lineno + 1
            if n > MAX_FUNCTION_LINES:
                long.append(f"app/{rel}:{fn.lineno} {fn.name} ({n} lines)")
    assert not long, long


def test_core_imports_no_upper_layer():
    """Data flows io → core → pipeline → cli/web: app.core never imports io, pipeline, web, the
    simulator, the configuration or the research filters."""
    bad = []
    for path in sorted((APP / "core").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            mods = []
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                mods = [node.module]
            for m in mods:
                parts = m.split(".")
                if parts[0] == "app" and len(parts) > 1 and parts[1] != "core":
                    bad.append(f"{path.name}: {m}")
    assert not bad, bad


def test_jsonsafe_imports_no_app_module():
    """app.jsonsafe serves io, pipeline and web alike: it depends on nothing of the application."""
    tree = ast.parse((APP / "jsonsafe.py").read_text(encoding="utf-8"))
    mods = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    mods += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level == 0]
    assert not [m for m in mods if m == "app" or m.startswith("app.")], mods
    assert not [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level > 0]
