"""The documentation stands alone and points only at what exists.

* No file outside ``tests/`` sends the reader to files that are not part of the repository (notes kept
  beside a checkout, or the folder beside it); the facts belong in ``docs/``.
* Every relative link in the Markdown pages leads to an existing file inside the repository.
* Every repository path written in backticks in ``docs/*.md`` and ``README.md`` (``ingest/steps.py``,
  ``model/train/stage1.py``, ``tests/test_raster_*.py``) exists, and every dotted module reference
  (``relightanyone.model.fit.fitter.Fitter``, ``align.colour.apply_ccm``) names an existing module and a
  name defined at its top level. ``CHANGELOG.md`` is history and may name paths that no longer exist.
"""

from __future__ import annotations

import ast
import functools
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Names of files that live outside the repository; ``../shared`` is the folder beside a checkout.
OUTSIDE_REFERENCE = re.compile(r"DESIGN|datasets\.md|rgca_reference|engines_reference|user_needs|\.\./shared")
# Source folder of each layer as it is imported (``relightanyone.<layer>`` or the short ``<layer>.``).
LAYER_DIRS = {
    "render": "render",
    "align": "align",
    "ingest": "ingest",
    "model": "model",
    "evaluation": "evaluation",
    "pipelines": "pipelines",
    "synth": "synth",
    "format": "relightanyone/format",
}
PATH_ROOTS = ("relightanyone", "bench", "tests", "docs", *LAYER_DIRS)
REPO_PATH = re.compile(rf"^(?:{'|'.join(PATH_ROOTS)})/[\w.*/-]*$")
MODULE_REFERENCE = re.compile(
    rf"^(?:relightanyone\.)?(?:{'|'.join(LAYER_DIRS)})(?:\.\w+)+$|^relightanyone(?:\.\w+)+$"
)
# A dotted span ending in one of these is a file name (``evaluation.json``), not a module.
FILE_SUFFIXES = frozenset("md json jsonl py yaml yml txt obj arrow exr png html csv".split())
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
CODE_SPAN = re.compile(r"`([^`\n]+)`")
LINK = re.compile(r"\[[^\]\n]*\]\(([^)\s]+)\)")


def repository_files() -> list[Path]:
    """Tracked and new (not ignored) files of the checkout; without git, the source folders and root files."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.splitlines()
        return [REPO / name for name in listed if (REPO / name).is_file()]
    except (OSError, subprocess.CalledProcessError):
        roots = [REPO / name for name in (*PATH_ROOTS, "pipelines")]
        files = [p for root in roots if root.is_dir() for p in root.rglob("*") if p.is_file()]
        return files + [p for p in REPO.iterdir() if p.is_file()]


def outside_references(path: Path, text: str) -> list[str]:
    """``file:line: ...`` for every line of ``text`` that names a file outside the repository."""
    return [
        f"{path}:{number}: names a file outside the repository: {line.strip()}"
        for number, line in enumerate(text.splitlines(), start=1)
        if OUTSIDE_REFERENCE.search(line)
    ]


def broken_links(path: Path, text: str) -> list[str]:
    """Relative Markdown links of ``text`` (written in ``path``) that lead nowhere or out of the repository."""
    problems = []
    for target in LINK.findall(FENCE.sub("", text)):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL or an anchor on the same page
        resolved = (path.parent / target.split("#", 1)[0]).resolve()
        if not resolved.is_relative_to(REPO):
            problems.append(f"{path.name}: link {target} leaves the repository")
        elif not resolved.exists():
            problems.append(f"{path.name}: link {target} leads to no file")
    return problems


@functools.cache
def top_level_names(module_file: Path) -> frozenset[str]:
    """Names a module defines or imports at its top level."""
    names = set()
    for node in ast.parse(module_file.read_text(), str(module_file)).body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(t.id for t in node.targets if isinstance(t, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((alias.asname or alias.name).split(".")[0] for alias in node.names)
    return frozenset(names)


def module_reference_problem(reference: str) -> str | None:
    """Why ``reference`` (``relightanyone.x.y.name`` or ``x.y.name``) names nothing, or None."""
    parts = reference.split(".")
    if parts[0] == "relightanyone":
        parts = parts[1:]
        if parts and parts[0] in LAYER_DIRS and parts[0] != "format":
            base, rest = REPO / LAYER_DIRS[parts[0]], parts[1:]
        else:
            base, rest = REPO / "relightanyone", parts
    else:
        base, rest = REPO / LAYER_DIRS[parts[0]], parts[1:]
    while rest and ((base / rest[0]).is_dir() or (base / f"{rest[0]}.py").is_file()):
        base = base / rest[0] if (base / rest[0]).is_dir() else base / f"{rest[0]}.py"
        rest = rest[1:]
    if not rest:
        return None
    module = base / "__init__.py" if base.is_dir() else base
    if not module.is_file():
        return f"no module {module.relative_to(REPO)}"
    if rest[0] not in top_level_names(module):
        return f"{module.relative_to(REPO)} defines no {rest[0]!r}"
    return None


def missing_paths(path: Path, text: str) -> list[str]:
    """Repository paths and module references in the backticks of ``text`` that do not exist."""
    problems = []
    for span in CODE_SPAN.findall(FENCE.sub("", text)):
        span = span.strip()
        if REPO_PATH.match(span) and ("." in span.rsplit("/", 1)[-1] or span.endswith("/")):
            if not any(REPO.glob(span.rstrip("/"))):
                problems.append(f"{path.name}: `{span}` does not exist")
        elif MODULE_REFERENCE.match(span) and span.rsplit(".", 1)[-1] not in FILE_SUFFIXES:
            problem = module_reference_problem(span)
            if problem:
                problems.append(f"{path.name}: `{span}`: {problem}")
    return problems


def markdown_pages() -> list[Path]:
    return [*sorted((REPO / "docs").glob("*.md")), REPO / "README.md", REPO / "CHANGELOG.md"]


def test_nothing_outside_tests_names_files_outside_the_repository() -> None:
    problems = []
    for path in repository_files():
        relative = path.relative_to(REPO)
        if relative.parts[0] == "tests":
            continue
        try:
            text = path.read_text()
        except (UnicodeDecodeError, OSError):
            continue  # binary files
        problems += outside_references(relative, text)
    assert not problems, "\n".join(problems)


def test_every_relative_link_between_pages_exists() -> None:
    problems = [p for page in markdown_pages() for p in broken_links(page, page.read_text())]
    assert not problems, "\n".join(problems)


def test_every_repository_path_and_module_named_in_the_docs_exists() -> None:
    pages = [page for page in markdown_pages() if page.name != "CHANGELOG.md"]
    problems = [p for page in pages for p in missing_paths(page, page.read_text())]
    assert not problems, "\n".join(problems)


def test_the_architecture_and_conventions_pages_exist_and_are_linked_from_the_readme() -> None:
    readme = (REPO / "README.md").read_text()
    for page in ("docs/architecture.md", "docs/conventions.md", "CHANGELOG.md"):
        assert (REPO / page).is_file(), page
        assert f"]({page})" in readme, f"README.md does not link {page}"


@pytest.mark.parametrize(
    ("checker", "text", "expected"),
    [
        (outside_references, "Conventions are DESIGN §3.\n", "outside the repository"),
        (outside_references, "see ../shared/fixtures/real\n", "outside the repository"),
        (broken_links, "See [the format](format.md) and [nothing](no_such_page.md).\n", "no_such_page.md"),
        (broken_links, "[up](../../outside.md)\n", "leaves the repository"),
        (missing_paths, "Read `model/train/no_such_module.py` first.\n", "does not exist"),
        (missing_paths, "Files `tests/test_no_such_*.py`.\n", "does not exist"),
        (missing_paths, "Call `relightanyone.model.relight.relight`.\n", "defines no 'relight'"),
        (missing_paths, "Call `align.colour.no_such_function`.\n", "defines no 'no_such_function'"),
    ],
)
def test_a_planted_problem_is_found(checker, text, expected) -> None:
    """The checkers are not vacuous: one planted reference of each kind is reported."""
    problems = checker(REPO / "docs" / "planted.md", text)
    assert len(problems) == 1 and expected in problems[0], problems


def test_text_that_is_fine_passes_the_checkers() -> None:
    text = (
        "See [format](format.md), [the web](https://example.org/x.md) and [below](#tables). Files\n"
        "`ingest/steps.py`, `tests/test_raster_*.py`, `render/csrc/`, `manifest.json`, `evaluation.json`;\n"
        "modules `relightanyone.model.fit.fitter.Fitter`, `format.schema`, `relightanyone.compiled`.\n"
        "```\ncalibration/sparse/0/   `model/not/checked/inside/fences.py`\n```\n"
    )
    page = REPO / "docs" / "planted.md"
    assert broken_links(page, text) == [] and missing_paths(page, text) == []
    assert outside_references(page, text) == []
