"""The paper map in training/__init__.py: complete, every name in it real, every citation right."""

from __future__ import annotations

import ast
import importlib
import io
import re
import tokenize
from pathlib import Path
from typing import Any

from repnet import core
from repnet import train as training

CITATION = re.compile(r"\b(Eq\. \d+(?:-\d+)?|Sec\. \d+(?:\.\d+)+)")
AUTHORS = "Wandt & Rosenhahn 2019"
SOURCES = sorted(Path(training.__file__).parent.glob("*.py")) + sorted(
    Path(core.__file__).parent.glob("*.py")
)


def _paper_map() -> dict[str, dict[str, list[str]]]:
    """{"Eq. 5-6": {"code": [dotted names], "test": [tests.training test names]}} from the docstring."""
    entries: dict[str, dict[str, list[str]]] = {}
    current = None
    for line in (training.__doc__ or "").splitlines():
        head = re.match(r"^(Eq\. \d+(?:-\d+)?|Sec\. \d+(?:\.\d+)+)\s+\S", line)
        item = re.match(r"^\s+(code|test): (\S+)$", line)
        if head:
            current = head[1]
            entries[current] = {"code": [], "test": []}
        elif item and current:
            entries[current][item[1]].append(item[2] if item[1] == "code" else f"tests.training.{item[2]}")
        elif not line.strip():
            current = None
    return entries


def _resolve(dotted: str) -> Any:
    """The object a dotted name names: the longest importable module, then attributes."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            found: Any = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for name in parts[cut:]:
            found = getattr(found, name)
        return found
    raise ImportError(dotted)


def test_the_map_covers_every_equation_of_the_paper_and_the_symmetry_error() -> None:
    entries = _paper_map()
    numbers = set()
    for key in entries:
        if key.startswith("Eq. "):
            first, _, last = key.removeprefix("Eq. ").partition("-")
            numbers |= set(range(int(first), int(last or first) + 1))
    assert numbers == set(range(1, 11))
    assert "Sec. 4.3" in entries
    for key, entry in entries.items():
        assert entry["code"] and entry["test"], key


def test_every_function_and_test_the_map_names_exists() -> None:
    for key, entry in _paper_map().items():
        for dotted in entry["code"] + entry["test"]:
            assert _resolve(dotted) is not None, (key, dotted)
        for dotted in entry["test"]:
            assert callable(_resolve(dotted)) and dotted.rsplit(".", 1)[1].startswith("test_"), dotted


def _citations(path: Path) -> list[tuple[int, str, str, str]]:
    """(line, citation, the docstring or comment it stands in, the dotted name of its place) for
    every paper citation in a module's docstrings and comments."""
    source = path.read_text()
    tree = ast.parse(source)
    module = f"{'repnet.core' if path.parent.name == 'core' else 'repnet.train'}.{path.stem}"
    scopes: list[tuple[int, int, str]] = []  # (first line, last line, dotted name) of defs and classes
    texts: list[tuple[int, int, str]] = []  # (first line, last line, text) of docstrings

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = f"{prefix}.{child.name}"
                scopes.append((child.lineno, child.end_lineno or child.lineno, name))
                body = child.body[0]
                if isinstance(body, ast.Expr) and isinstance(body.value, ast.Constant):
                    texts.append((body.lineno, body.end_lineno or body.lineno, str(body.value.value)))
                visit(child, name)

    visit(tree, module)
    first = tree.body[0] if tree.body else None
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
        texts.append((first.lineno, first.end_lineno or first.lineno, str(first.value.value)))
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        if token.type == tokenize.COMMENT:
            texts.append((token.start[0], token.start[0], token.string))

    def place(line: int) -> str:
        inside = [(last - start, name) for start, last, name in scopes if start <= line <= last]
        if inside:
            return min(inside)[1]
        after = [s for s in tree.body if s.lineno >= line and isinstance(s, ast.Assign | ast.AnnAssign)]
        if after:
            target = after[0].targets[0] if isinstance(after[0], ast.Assign) else after[0].target
            return f"{module}.{ast.unparse(target)}"
        return module

    found = []
    for start, last, text in texts:
        for match in CITATION.finditer(text):
            line = start + text[: match.start()].count("\n") if start != last else start
            found.append((line, match[1], text, place(line)))
    return found


def test_every_citation_in_training_is_the_equation_the_map_gives_to_that_code() -> None:
    entries = _paper_map()
    cited = 0
    for path in SOURCES:
        if path.name == "__init__.py":
            continue
        for line, citation, text, name in _citations(path):
            where = f"{path.name}:{line} ({name}) cites {citation}"
            assert AUTHORS in " ".join(text.split()), f"{where} without '{AUTHORS}'"
            assert citation in entries, f"{where}: the paper map has no {citation}"
            owners = entries[citation]["code"]
            assert any(name == o or name.startswith(o + ".") for o in owners), f"{where}; the map: {owners}"
            cited += 1
    assert cited >= 10  # the check reads what it should
