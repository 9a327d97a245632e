"""Checks on the repository as a newcomer meets it (issue 33): every relative link in its Markdown
resolves, and no module of the node or the kit imports another that imports it back."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SKIPPED = {".venv", "target", ".git", "node_modules", ".device"}
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def markdown_files() -> list[Path]:
    return sorted(p for p in ROOT.rglob("*.md")
                  if not SKIPPED & set(p.relative_to(ROOT).parts) and "corpus" not in p.parts)


def broken_links(path: Path) -> list[str]:
    """The relative links of one Markdown file whose target file or folder does not exist."""
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)  # code blocks hold no links
    broken = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL, or an anchor within the file
        if not (path.parent / target.split("#", 1)[0]).exists():
            broken.append(target)
    return broken


def test_every_relative_link_in_the_markdown_resolves():
    files = markdown_files()
    assert ROOT / "README.md" in files and ROOT / "docs" / "tracking.md" in files
    broken = {str(p.relative_to(ROOT)): b for p in files if (b := broken_links(p))}
    assert not broken, f"links to nothing: {broken}"


def test_a_broken_link_is_found(tmp_path):
    (tmp_path / "there.md").write_text("x")
    page = tmp_path / "page.md"
    page.write_text("[ok](there.md#a) [url](https://example.org) [anchor](#b) [gone](missing.md)\n"
                    "```\n[in code](nowhere.md)\n```\n")
    assert broken_links(page) == ["missing.md"]


def paths(root: str, text: str) -> list[str]:
    """The paths after `root::` in `text`, a group `a::{b, c::D}` read as `a::b` and `a::c::D`."""
    found = []
    for prefix, group in re.findall(rf"\b{root}::([A-Za-z_0-9:]*?)(?:\{{([^}}]*)\}}|(?=[^A-Za-z_0-9:]))", text):
        items = [item.strip() for item in group.split(",")] if group else [""]
        found += [prefix + item.split(" as ")[0] for item in items]
    return found


def rust_imports(src: Path) -> dict[str, set[str]]:
    """Module -> the modules it names in `crate::`/`super::` paths or re-exports from its children
    (tests left out), for every module under `src`."""
    modules = {}
    for file in src.rglob("*.rs"):
        parts = list(file.relative_to(src).with_suffix("").parts)
        if parts[-1] == "mod":
            parts = parts[:-1]
        if parts in (["lib"], ["main"]):
            continue
        modules["::".join(parts)] = file

    def resolve(base: str, path: str) -> str | None:
        names = path.split("::")
        for k in range(len(names), 0, -1):
            candidate = "::".join(filter(None, [base, *names[:k]]))
            if candidate in modules:
                return candidate
        return base if base in modules else None

    graph = {}
    for name, file in modules.items():
        text = re.split(r"#\[cfg\(test\)\]", re.sub(r"//.*", "", file.read_text()))[0]
        is_folder = file.name == "mod.rs"
        parent = name.rsplit("::", 1)[0] if "::" in name else ""
        found = {resolve(base, p) for base, root in (("", "crate"), (parent, "super")) for p in paths(root, text)}
        if is_folder:
            found |= {f"{name}::{c}" for c in re.findall(r"^\s*(?:pub(?:\([a-z]+\))? )?use (?:self::)?([a-z_0-9]+)::",
                                                          text, re.M)}
        graph[name] = {m for m in found if m in modules and m != name}
    return graph


def python_imports(package: Path) -> dict[str, set[str]]:
    """Module -> the package's modules it imports (`from .x import`, at any depth of the file)."""
    return {file.stem: set(re.findall(r"from \.(\w+) import", file.read_text())) - {file.stem}
            for file in package.glob("*.py")}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in list(graph):
        if v not in index:
            visit(v)
    return found


def test_modules_import_one_way():
    node = rust_imports(ROOT / "src")
    assert "sources::recording::mcap" in node and node["sources::recording"], "the walk sees the modules"
    assert cycles(node) == [], "node modules that import each other"
    kit = python_imports(ROOT / "models" / "gdvae")
    assert "train" in kit["cli"], "the walk sees the kit's imports"
    assert cycles(kit) == [], "kit modules that import each other"


def test_a_circle_of_imports_is_found(tmp_path):
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    (tmp_path / "src" / "x").mkdir(parents=True)
    (tmp_path / "src" / "x" / "mod.rs").write_text("mod y;\npub use y::Thing;\n")
    (tmp_path / "src" / "x" / "y.rs").write_text("use super::{Other, z};\n")
    (tmp_path / "src" / "z.rs").write_text("use crate::x::Thing;\n")
    assert cycles(rust_imports(tmp_path / "src")) == [["x", "x::y"]]
    assert paths("crate", "use crate::a::{b, c::D as E};\nlet x = crate::f::g(1);") == ["a::b", "a::c::D", "f::g"]
