"""The README's architecture section matches the tree, and the README explains the project
without anything outside the repository."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _architecture_block() -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Architecture"):]
    return section[section.index("```"):section.index("```", section.index("```") + 3)]


def test_every_module_is_in_the_architecture_section():
    block = _architecture_block()
    missing = [p.relative_to(ROOT).as_posix() for p in sorted((ROOT / "app").rglob("*.py"))
               if p.name != "__init__.py" and "__pycache__" not in p.parts
               and not re.search(rf"(?<![\w.]){re.escape(p.stem)}\b", block)]
    assert not missing, f"modules the README's architecture section does not name: {missing}"


def test_every_named_module_exists():
    block = _architecture_block()
    stems = {p.stem for p in (ROOT / "app").rglob("*.py")} | {p.name for p in (ROOT / "app").rglob("*") if p.is_dir()}
    named = set(re.findall(r"(?<![\w/])([a-z_]+)\.py", block))
    assert named <= stems, f"the README names modules that do not exist: {sorted(named - stems)}"


def test_readme_links_resolve_inside_the_repository():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "../shared" not in text and "SPEC.md" not in text
    for link in re.findall(r"\]\(([^)#]+)\)", text):
        if not link.startswith("http"):
            assert (ROOT / link).exists(), link
    for doc in ("docs/METHOD.md", "docs/CONTRACTS.md"):
        assert doc in text and (ROOT / doc).exists()
