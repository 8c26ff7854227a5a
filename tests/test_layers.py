"""The layer rules of the package, read from every import statement of every module (function bodies too).

Dependencies point one way: render <- align <- ingest <- model <- evaluation <- pipelines, with the
dataset format under ingest and model; synth is the judge and shares no code with what it judges. The
rules and the reasons are in ``docs/architecture.md``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from relightanyone.ingest.registry import ADAPTERS

REPO = Path(__file__).resolve().parents[1]
# Source folder -> the package it is imported as.
PACKAGE_FOLDERS = {
    "relightanyone": "relightanyone",
    "render": "relightanyone.render",
    "align": "relightanyone.align",
    "ingest": "relightanyone.ingest",
    "model": "relightanyone.model",
    "evaluation": "relightanyone.evaluation",
    "pipelines": "relightanyone.pipelines",
    "synth": "relightanyone.synth",
}
LAYERS = ("render", "align", "format", "ingest", "model", "evaluation", "pipelines", "synth")
# Layer -> the project layers it must not import. Root modules (``relightanyone.compiled``,
# ``relightanyone.parallel``, ...) are utilities every layer may use, except where listed.
FORBIDDEN = {
    "render": {"align", "format", "ingest", "model", "evaluation", "pipelines", "synth", "root"},
    "align": {"format", "ingest", "model", "evaluation", "pipelines", "synth", "root"},
    "format": {"ingest", "model", "evaluation", "pipelines", "synth"},
    "ingest": {"model", "evaluation", "pipelines", "synth"},
    "model": {"evaluation", "pipelines", "synth"},
    "evaluation": {"pipelines"},
    "pipelines": {"synth"},
    "synth": {"render", "align", "format", "ingest", "model", "evaluation", "pipelines", "root"},
}
# The compiled-kernel helper is the one root module render may use.
ROOT_ALLOWED_TO = {"render": {"relightanyone.compiled"}}


def module_files() -> dict[str, Path]:
    """Every module of the package: dotted name -> source file."""
    modules = {}
    for folder, package in PACKAGE_FOLDERS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            parts = list(path.relative_to(REPO / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join([package, *parts])] = path
    return modules


def imported_modules(path: Path, module: str) -> set[str]:
    """Absolute names of every project module ``path`` imports, at any depth of the file."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names.add(target)
            # ``from relightanyone.ingest import ava256`` imports the module ``...ingest.ava256``.
            names.update(f"{target}.{alias.name}" for alias in node.names)
    return {name for name in names if name == "relightanyone" or name.startswith("relightanyone.")}


def layer_of(module: str) -> str:
    """``relightanyone.model.fit.avatar`` -> "model"; root modules (``relightanyone.cli``) -> "root"."""
    parts = module.split(".")
    if len(parts) >= 2 and parts[1] in LAYERS:
        return parts[1]
    return "root"


def violations(modules: dict[str, Path]) -> list[str]:
    found = set()
    adapters = {f"relightanyone.ingest.{adapter.module}" for adapter in ADAPTERS.values()}
    for module, path in modules.items():
        layer = layer_of(module)
        if layer == "root":
            continue
        for target in imported_modules(path, module):
            if target not in modules and target.rpartition(".")[0] in modules:
                target = target.rpartition(".")[0]  # ``from module import name``
            if target not in modules:
                continue
            target_layer = layer_of(target)
            if target_layer == layer:
                own_adapter = next((a for a in adapters if module == a or module.startswith(a + ".")), None)
                if own_adapter and target in adapters and target != own_adapter:
                    found.add(f"{module} imports {target}: one ingest adapter may not import another")
                continue
            if target_layer == "root" and target in ROOT_ALLOWED_TO.get(layer, set()):
                continue
            if target_layer in FORBIDDEN[layer]:
                found.add(f"{module} imports {target}: {layer} may not import {target_layer}")
    return sorted(found)


def test_every_module_keeps_the_layer_rules() -> None:
    problems = violations(module_files())
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize(
    ("module", "statement", "expected"),
    [
        (
            "relightanyone.render.camera",
            "from relightanyone.ingest.calibration import read_krt_json",
            "render",
        ),
        ("relightanyone.align.colour", "import relightanyone.format.codecs", "align"),
        ("relightanyone.ingest.steps", "from relightanyone.model.train import losses", "ingest"),
        ("relightanyone.format.reader", "from relightanyone.ingest.tracking import read_obj", "format"),
        ("relightanyone.model.networks.stage1", "from relightanyone.evaluation import metrics", "model"),
        ("relightanyone.synth.world", "from relightanyone.render.sh import sh_basis", "synth"),
        ("relightanyone.ingest.nersemble", "from relightanyone.ingest.ava256 import plan", "adapter"),
    ],
)
def test_a_planted_forbidden_import_is_found(tmp_path, module, statement, expected) -> None:
    """The checker is not vacuous: one forbidden import, even inside a function body, is reported."""
    modules = module_files()
    planted = tmp_path / "planted.py"
    planted.write_text(modules[module].read_text() + f"\n\ndef _planted():\n    {statement}\n")
    problems = violations({**modules, module: planted})
    assert problems and all(problem.startswith(f"{module} imports ") for problem in problems), problems
    assert all(("another" if expected == "adapter" else f"{expected} may not import") in p for p in problems)


def function_local_project_imports(path: Path) -> list[int]:
    """Line numbers of project imports inside function bodies of ``path``."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for inner in ast.walk(node):
                if isinstance(inner, ast.ImportFrom) and (
                    inner.level or (inner.module or "").startswith("relightanyone")
                ):
                    lines.append(inner.lineno)
                elif isinstance(inner, ast.Import) and any(
                    a.name.startswith("relightanyone") for a in inner.names
                ):
                    lines.append(inner.lineno)
    return sorted(set(lines))


def test_library_modules_import_the_project_at_module_top() -> None:
    """The dependency graph is visible at the top of each module; only command modules defer imports
    (so ``relightanyone --help`` does not load torch), as their docstrings say."""
    command_modules = {"cli.py", "command.py", "__main__.py"}
    hidden = {
        module: lines
        for module, path in module_files().items()
        if path.name not in command_modules and (lines := function_local_project_imports(path))
    }
    assert not hidden, hidden
