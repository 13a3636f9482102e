"""The research filters stay out of the product: nothing outside app/research imports them."""

import ast
from pathlib import Path

APP = Path(__file__).resolve().parents[2] / "app"


def _imported_modules(path: Path) -> set[str]:
    mods = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            mods.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            mods.add(node.module)
            mods.update(f"{node.module}.{a.name}" for a in node.names)
    return mods


def test_product_never_imports_research():
    offenders = []
    for path in sorted(APP.rglob("*.py")):
        if path.relative_to(APP).parts[0] == "research":
            continue
        bad = sorted(m for m in _imported_modules(path) if m == "app.research" or m.startswith("app.research."))
        if bad:
            offenders.append(f"{path.relative_to(APP.parent)}: {', '.join(bad)}")
    assert not offenders, offenders


def test_research_imports_only_core():
    """app/research builds on app.core; it never reaches up into pipeline, web, io or the simulator."""
    for path in sorted((APP / "research").glob("*.py")):
        app_mods = {m.split(".")[1] for m in _imported_modules(path) if m.startswith("app.") and m.count(".") >= 1}
        assert app_mods <= {"core", "research"}, (path.name, app_mods)
