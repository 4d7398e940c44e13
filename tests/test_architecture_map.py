"""The dependency rules of docs/architecture.md, checked on the code: every import of every module
(inside functions and TYPE_CHECKING blocks too) and every import by name (a string that is a package
module's name, ``"kklcasadi.train.bank"`` or ``"kklcasadi.train.bank:train_bank"``, or the argument of
``importlib.import_module``) is one its row of the table allows, the import graph has no circle, and
torch stays on the training side."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kklcasadi"
DOC = ROOT / "docs" / "architecture.md"
#: may import torch inside functions (the benchmarks time torch; the CLI trains)
TORCH_IN_FUNCTIONS = ("train", "evaluation.bench", "cli")


def _table() -> dict[str, set[str]]:
    """The table of docs/architecture.md: module or room -> what it may import."""
    text = DOC.read_text()
    section = text.split("## Modules and what each may import", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[0].startswith("`"):
            continue
        name = cells[0].strip("`")
        rows[name] = set() if cells[2] == "-" else {c.strip() for c in cells[2].split(",")}
    return rows


TABLE = _table()


def _dotted(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _is_module(dotted: str) -> bool:
    target = PACKAGE.joinpath(*dotted.split("."))
    return target.with_suffix(".py").exists() or (target / "__init__.py").exists()


def _imports(path: Path) -> list[tuple[str, bool]]:
    """``(module, at_module_level)`` for every import in the file; package modules relative to ``kklcasadi``
    ("" for the package itself), others absolute with a leading ``!``."""
    tree = ast.parse(path.read_text())
    top = {id(node) for node in tree.body}
    package = _dotted(path).split(".") if path.name == "__init__.py" else _dotted(path).split(".")[:-1]
    package = [p for p in package if p]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                name = alias.name
                inside = name == "kklcasadi" or name.startswith("kklcasadi.")
                found.append((name[len("kklcasadi."):] if inside and "." in name else ("" if inside else "!" + name),
                              id(node) in top))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
            elif node.module and (node.module == "kklcasadi" or node.module.startswith("kklcasadi.")):
                base = []
                node_module = node.module[len("kklcasadi"):].lstrip(".")
                module = ".".join([*base, *([node_module] if node_module else [])])
                found += _from_names(module, node, id(node) in top)
                continue
            else:
                found.append(("!" + (node.module or ""), id(node) in top))
                continue
            module = ".".join([*base, *([node.module] if node.module else [])])
            found += _from_names(module, node, id(node) in top)
    return found


#: A string that is a package module's name: ``kklcasadi.a.b``, then ``.name`` or ``:name`` (an import by name).
_NAMED = re.compile(r"kklcasadi((?:\.[A-Za-z_]\w*)+)(?::[A-Za-z_]\w*)?")


def _longest_module(parts: list[str]) -> str | None:
    for n in range(len(parts), 0, -1):
        if _is_module(".".join(parts[:n])):
            return ".".join(parts[:n])
    return None


def _named_modules(source: str, package: tuple[str, ...] = ()) -> list[str]:
    """The package modules the code imports by name, relative to ``kklcasadi``: each string constant that is
    a module's name (``kklcasadi.a.b``, ``kklcasadi.a.b:attribute``, ``kklcasadi.a.b.attribute``: the longest
    prefix that is a module), and the first argument of ``importlib.import_module`` (relative ones resolved in
    ``package``, the module's package below ``kklcasadi``). Prose that mentions a module is not an import."""
    tree = ast.parse(source)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            match = _NAMED.fullmatch(node.value)
            if match and (module := _longest_module(match.group(1)[1:].split("."))):
                found.append(module)
        elif (isinstance(node, ast.Call) and ast.unparse(node.func) in ("importlib.import_module", "import_module")
              and node.args and isinstance(node.args[0], ast.Constant) and str(node.args[0].value).startswith(".")):
            name = str(node.args[0].value)
            level = len(name) - len(name.lstrip("."))
            base = list(package[:len(package) - level + 1])
            if (module := _longest_module([*base, *name.lstrip(".").split(".")])) is not None:
                found.append(module)
    return found


def _from_names(module: str, node: ast.ImportFrom, top: bool) -> list[tuple[str, bool]]:
    """``from module import a, b``: the submodules a, b where they are modules, else the module."""
    out = []
    for alias in node.names:
        sub = f"{module}.{alias.name}" if module else alias.name
        out.append((sub if _is_module(sub) else module, top))
    return out


def _row(dotted: str) -> str | None:
    """The most specific row of the table that covers the module."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in TABLE:
            return ".".join(parts[:n])
    return None


def _covered(target: str, allowed: set[str]) -> bool:
    return any(target == a or target.startswith(a + ".") for a in allowed)


SOURCES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__main__.py" and p != PACKAGE / "__init__.py")


def test_the_table_is_read_from_the_page():
    assert {"validation", "plant.systems", "observer.kkl", "train", "cli"} <= set(TABLE)
    assert TABLE["validation"] == set() and "observer.kkl" in TABLE["observer.codegen"]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: _dotted(p) or "__init__")
def test_every_import_follows_the_table(path):
    _check_dependencies(_dotted(path), path.name == "__init__.py", _imports(path), _named(path))


def _named(path: Path) -> list[str]:
    dotted = _dotted(path).split(".") if path.name == "__init__.py" else _dotted(path).split(".")[:-1]
    return _named_modules(path.read_text(), tuple(p for p in dotted if p))


def _check_dependencies(dotted: str, is_init: bool, imports: list[tuple[str, bool]], named: list[str]) -> None:
    """Fail where an import, or a string naming a module, is not one the module's row allows."""
    row = _row(dotted)
    room = dotted if is_init else None
    assert row is not None or room is not None, f"{dotted}: add it to the table of docs/architecture.md"
    allowed = set(TABLE.get(row, ())) | ({room} if room else set())
    for target in named:
        if (row is not None and (target == row or target.startswith(row + "."))) or dotted.startswith(target + "."):
            continue                                         # its own row, or a room it is in (a format's name)
        assert _covered(target, allowed), f"{dotted} names {target} in a string, which its row of " \
                                          f"docs/architecture.md does not allow ({sorted(allowed)})"
    for target, at_top in imports:
        if target.startswith("!"):
            name = target[1:].split(".")[0]
            if name == "torch":
                assert row in TORCH_IN_FUNCTIONS, f"{dotted} imports torch"
                assert row == "train" or not at_top, f"{dotted} imports torch at module level (only inside functions)"
            continue
        assert target != "", f"{dotted} imports the front door kklcasadi/__init__.py; import the module instead"
        if row is not None and (target == row or target.startswith(row + ".")):
            continue                                                  # within its own row
        assert _covered(target, allowed), f"{dotted} imports {target}, which its row of docs/architecture.md " \
                                          f"does not allow ({sorted(allowed)})"
        if target.split(".")[0] == "train" and row != "train":
            assert not at_top, f"{dotted} imports {target} at module level (the training side, only inside functions)"


def test_a_string_naming_a_forbidden_module_fails():
    """The model layer naming a training hook by string is a dependency the table forbids."""
    source = ('import importlib\n\nclass Bank:\n    """Trained by kklcasadi.train.bank (prose: no dependency)."""\n'
              '    trainer = "kklcasadi.train.bank:train_bank"\n\n'
              'def load():\n    return importlib.import_module("...train.phase1", __package__)\n')
    assert _named_modules(source, ("model", "variants")) == ["train.bank", "train.phase1"]
    with pytest.raises(AssertionError, match="model.variants.bank names train.bank in a string"):
        _check_dependencies("model.variants.bank", False, [], _named_modules(source))
    _check_dependencies("cli.train", False, [], _named_modules(source))          # the CLI may name it


def _graph() -> dict[str, set[str]]:
    graph = {}
    for path in SOURCES:
        dotted = _dotted(path)
        targets = [t for t, _ in _imports(path)] + [t for t in _named(path) if not dotted.startswith(t + ".")]
        graph[dotted] = {t for t in targets if not t.startswith("!") and t and t != dotted}
    return graph


def test_the_import_graph_has_no_circle():
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                circle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import circle: " + " -> ".join(circle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)


def test_the_circle_check_can_fail(monkeypatch, tmp_path):
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}}
    monkeypatch.setattr(__import__(__name__), "_graph", lambda: graph)
    with pytest.raises(pytest.fail.Exception, match="a -> b -> c -> a"):
        test_the_import_graph_has_no_circle()


def test_the_rows_follow_the_import_order():
    """Each row of the table may import only rows above it and its own: the table states the real order (a
    module with a row of its own inside a room, such as ``observer.codegen.kernels``, by that row)."""
    rows = list(TABLE)
    for i, name in enumerate(rows):
        for target in TABLE[name]:
            if target == "-" or target == name or name.startswith(target + "."):
                continue
            below = [r for r in rows[i + 1:] if r == target or r.startswith(target + ".")
                     or (target.startswith(r + ".") and _row(target) == r)]
            assert not below, f"docs/architecture.md: {name} may import {target}, whose row {below[0]} comes below it"


def test_every_row_names_existing_code():
    for name, allowed in TABLE.items():
        assert _is_module(name), f"docs/architecture.md names {name}, which is not in kklcasadi/"
        for target in allowed:
            assert target == "-" or _is_module(target), f"{name} may import {target}, which does not exist"


#: Longest module without a reason written at its top (issue 44: rooms of one concern).
LONG_MODULE = 600


@pytest.mark.parametrize("path", sorted(PACKAGE.rglob("*.py")), ids=lambda p: str(p.relative_to(ROOT)))
def test_a_long_module_says_why_at_its_top(path):
    lines = path.read_text().count("\n")
    if lines > LONG_MODULE:
        docstring = ast.get_docstring(ast.parse(path.read_text())) or ""
        assert f"Over {LONG_MODULE} lines:" in docstring, (
            f"{path.relative_to(ROOT)} has {lines} lines: split it into rooms of one concern, or say why not in "
            f"its docstring (a paragraph starting 'Over {LONG_MODULE} lines:')")


def test_the_front_door_is_small():
    import kklcasadi

    assert len(kklcasadi.__all__) <= 20
    doc = DOC.read_text()
    for name in re.findall(r"`(\w+)`", doc.split("is the front door:", 1)[1].split(" and nothing", 1)[0]):
        assert name in kklcasadi.__all__, name
