"""The dependency rules of docs/architecture.md, checked on the code: every module imports (at
module level) only the kklcasadi modules its layer allows, and the deploy side never torch."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "kklcasadi"

#: module -> the kklcasadi modules it may import at module level (docs/architecture.md)
ALLOWED = {
    "validation": set(),
    "rk4": set(),
    "metrics": set(),
    "windows": {"validation"},
    "systems": {"validation"},
    "signals": {"validation"},
    "design": {"systems", "validation"},
    "simulate": {"systems", "signals", "rk4", "validation"},
    "architecture": {"validation"},
    "casadi_nets": {"architecture", "validation"},
    "variants": {"architecture", "casadi_nets", "filterbank", "systems", "validation", "variants"},
    "modelfile": {"variants", "architecture", "validation", "design", "systems"},
    "observer": {"modelfile", "variants", "systems", "rk4", "windows", "validation"},
    "codegen": {"observer", "validation", "casadi_nets"},
    "interop": {"observer"},
    "data": {"systems", "design", "simulate", "signals", "windows", "validation"},
    "ekf": {"systems", "rk4", "validation"},
    "pf": {"simulate", "systems", "validation"},
    "protocol": {"signals", "simulate", "systems", "metrics", "validation"},
    "report": {"protocol", "signals", "metrics", "systems"},
    "filterbank": {"architecture", "casadi_nets", "validation"},
    "mhe": {"rk4", "systems", "validation"},
    "nmpc": {"ekf", "mhe", "rk4", "systems", "validation"},
    "certificate": {"architecture", "casadi_nets", "data", "design", "observer", "protocol", "simulate",
                    "validation", "windows"},
    "trialcache": {"simulate", "systems", "__version__"},
    "compiled": {"trialcache"},
    "pipelines": {"metrics", "systems", "ekf", "mhe", "observer", "protocol", "validation"},
}
#: modules that may import torch at module level
TORCH = {"train"}
#: the command line and the benchmarks may import anything (torch only inside functions)


def _module_imports(path: Path) -> set[str]:
    """Absolute names of the modules imported at module level (TYPE_CHECKING blocks excluded)."""
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    package = parts[:-1]                                   # the package a relative import starts from
    found = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom):
            start = package[:len(package) - node.level + 1] if node.level else ()
            module = ".".join([*start, *(node.module.split(".") if node.module else [])])
            found |= {f"{module}.{a.name}" for a in node.names} if node.module is None else {module}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return found


def _top(name: str) -> str:
    parts = name.split(".")
    return parts[1] if parts[0] == "kklcasadi" and len(parts) > 1 else parts[0]


@pytest.mark.parametrize("module", sorted(ALLOWED))
def test_module_imports_follow_the_layers(module):
    path = PACKAGE / f"{module}.py"
    paths = [path] if path.exists() else sorted((PACKAGE / module).glob("*.py"))
    for source in paths:
        imports = _module_imports(source)
        internal = {_top(n) for n in imports if n.startswith("kklcasadi")} - {module}
        assert internal <= ALLOWED[module], f"{source.name} imports {sorted(internal - ALLOWED[module])}"
        assert not any(n.split(".")[0] == "torch" for n in imports), f"{source.name} imports torch"


def test_every_module_is_in_the_map():
    modules = {p.stem for p in PACKAGE.glob("*.py")} | {p.name for p in PACKAGE.iterdir()
                                                        if p.is_dir() and (p / "__init__.py").exists()}
    unmapped = modules - set(ALLOWED) - TORCH - {"__init__", "cli", "bench"}
    assert not unmapped, f"add {sorted(unmapped)} to docs/architecture.md and ALLOWED"


def test_benchmarks_import_torch_only_inside_functions():
    for source in sorted((PACKAGE / "bench").glob("*.py")) + [PACKAGE / "cli.py"]:
        imports = _module_imports(source)
        assert not any(n.split(".")[0] == "torch" or ".train" in n for n in imports), source.name
