"""The README and docs/ against the code: the ownership table, the Architecture tree, the links.

What is generated from the code (the parameters' table) must appear verbatim, the tree must name
every subpackage that exists and none that does not, and every relative link (and its heading
anchor) must resolve.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from dbml.protocol.schema import ownership_table

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
PACKAGE = ROOT / "src" / "dbml"

_FENCE = re.compile(r"```[a-z]*\n(.*?)```", re.S)
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_ENTRY = re.compile(r"^  (?P<name>[a-z_][a-z0-9_]*)(?P<kind>/|\.py)\s")
"""A top-level line of the tree: two spaces, then ``name/`` or ``name.py``."""


def architecture_tree() -> str:
    """The first fenced block after the README's ``## Architecture`` heading."""
    text = README.read_text()
    _, heading, rest = text.partition("\n## Architecture\n")
    assert heading, "README.md has no '## Architecture' section"
    section = rest.split("\n## ", 1)[0]
    block = _FENCE.search(section)
    assert block is not None, "no fenced block under '## Architecture'"
    return block.group(1)


def tree_entries(tree: str) -> dict[str, str]:
    """Each top-level entry (``core/``, ``secure.py``) and its text, continuation lines included."""
    entries: dict[str, str] = {}
    current: str | None = None
    for line in tree.splitlines():
        match = _ENTRY.match(line + " ")
        if match:
            current = match["name"] + match["kind"]
            entries[current] = line
        elif current is not None and line.startswith("    "):
            entries[current] += " " + line.strip()
    return entries


def subpackages() -> list[str]:
    """Every package below ``src/dbml`` (``core``, ``experiment/analysis``), as paths."""
    return sorted(
        str(init.parent.relative_to(PACKAGE))
        for init in PACKAGE.rglob("__init__.py")
        if init.parent != PACKAGE and "__pycache__" not in init.parts
    )


def top_level_modules() -> list[str]:
    """Single-module packages at the top (``secure.py``), not ``__init__`` or ``__main__``."""
    return sorted(p.name for p in PACKAGE.glob("*.py") if not p.name.startswith("__"))


def test_the_ownership_table_is_the_schemas_own() -> None:
    table = ownership_table()
    holders = [p.name for p in (README, *DOCS) if table in p.read_text()]
    assert holders, (
        "neither README.md nor docs/*.md contains ownership_table() verbatim; paste the output "
        "of: python -c 'from dbml.protocol.schema import ownership_table; "
        "print(ownership_table())'"
    )


def test_the_architecture_tree_names_every_subpackage() -> None:
    entries = tree_entries(architecture_tree())
    missing = []
    for package in subpackages():
        top, _, nested = package.partition("/")
        if f"{top}/" not in entries:
            missing.append(f"{top}/")
        elif nested and f"{nested.rsplit('/', 1)[-1]}/" not in entries[f"{top}/"]:
            missing.append(f"{package}/ (under {top}/)")
    for module in top_level_modules():
        if module not in entries and f"{module.removesuffix('.py')}/" not in entries:
            missing.append(module)
    assert not missing, f"the Architecture tree omits {missing}"


def test_the_architecture_tree_names_every_module_on_its_packages_lines() -> None:
    entries = tree_entries(architecture_tree())
    missing = []
    for package in subpackages():
        top = package.partition("/")[0]
        words = set(re.findall(r"[a-z0-9_]+", entries.get(f"{top}/", "")))
        missing += [
            f"{package}/{module.name}"
            for module in (PACKAGE / package).glob("*.py")
            if module.stem != "__init__" and module.stem not in words
        ]
    assert not missing, f"the Architecture tree's lines omit {sorted(missing)}"


def test_the_architecture_tree_names_nothing_that_is_gone() -> None:
    packages = {p.partition("/")[0] for p in subpackages()}
    stale = [
        name
        for name in tree_entries(architecture_tree())
        if (name.endswith("/") and name[:-1] not in packages)
        or (name.endswith(".py") and not (PACKAGE / name).is_file())
    ]
    assert not stale, f"the Architecture tree names {stale}, which src/dbml does not have"


def anchors(document: Path) -> set[str]:
    """The anchors GitHub gives ``document``'s headings (``## ROS 2`` -> ``ros-2``)."""
    text = _FENCE.sub("", document.read_text())
    headings = re.findall(r"^#+ (.+)$", text, re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


@pytest.mark.parametrize("document", [README, *DOCS], ids=lambda p: p.name)
def test_every_relative_link_resolves(document: Path) -> None:
    text = _FENCE.sub("", document.read_text())  # code is not links
    broken = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):
            continue  # http:, https:, mailto:
        path, _, anchor = target.partition("#")
        linked = document.parent / path if path else document
        unknown_heading = anchor and linked.suffix == ".md" and anchor not in anchors(linked)
        if not linked.exists() or unknown_heading:
            broken.append(target)
    assert not broken, f"{document.name}: links to missing files or headings {broken}"


def test_the_first_screens_commands_exist() -> None:
    head = "\n".join(README.read_text().splitlines()[:30])
    assert "make run" in head
    assert "make test" in head
    targets = re.findall(r"^([a-z0-9-]+):", (ROOT / "Makefile").read_text(), re.M)
    assert {"run", "test"} <= set(targets)


def test_the_docs_are_linked_from_the_readme() -> None:
    readme = README.read_text()
    unlinked = [p.name for p in DOCS if f"(docs/{p.name}" not in readme]
    assert not unlinked, f"README.md does not link {unlinked}"
