"""The worked example of ``docs/ingest.md`` ("Your own capture") works as written.

The test reads the section's code blocks from the page itself: it runs the Python block that writes the
capture, checks that the files it wrote are the folder tree the page shows, then runs the page's
``relightanyone`` commands one by one through the CLI's error boundary and checks what they produced.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from PIL import Image

from relightanyone.cli import cli
from relightanyone.format.reader import NormalizedDataset
from relightanyone.render.mesh import read_obj

REPO = Path(__file__).resolve().parents[1]
SECTION = "## Your own capture"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.MULTILINE | re.DOTALL)


def _section_blocks() -> list[tuple[str, str]]:
    """``(language, text)`` of every fenced block of the section, in page order."""
    page = (REPO / "docs" / "ingest.md").read_text()
    start = page.index(SECTION)
    end = page.find("\n## ", start + len(SECTION))
    return FENCE.findall(page[start : end if end >= 0 else len(page)])


def _tree_files(tree: str) -> set[str]:
    """File paths of the folder tree block (first word of each line, nested under the top folder)."""
    lines = [line.split()[0] for line in tree.splitlines() if line.strip()]
    top = lines[0].rstrip("/")
    return {f"{top}/{name}" for name in lines[1:]}


@pytest.fixture(scope="module")
def worked_example(tmp_path_factory) -> tuple[Path, list[list[str]]]:
    """The capture written by the page's Python block in a fresh folder, and the page's commands."""
    blocks = _section_blocks()
    tree = next(text for language, text in blocks if language == "")
    script = next(text for language, text in blocks if language == "python")
    commands = next(text for language, text in blocks if language == "bash")
    folder = tmp_path_factory.mktemp("worked_example")
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(folder)
        exec(compile(script, "docs/ingest.md (worked example)", "exec"), {"__name__": "worked_example"})
    written = {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}
    assert written == _tree_files(tree)
    return folder, [shlex.split(line) for line in commands.splitlines() if line.strip()]


def test_worked_example_ingests_validates_and_inspects(worked_example, monkeypatch):
    folder, commands = worked_example
    assert [command[:2] for command in commands] == [
        ["relightanyone", "ingest"],
        ["relightanyone", "validate"],
        ["relightanyone", "inspect"],
    ]
    monkeypatch.chdir(folder)
    outputs = []
    for command in commands:
        result = CliRunner().invoke(cli, command[1:])
        assert result.exit_code == 0, f"{' '.join(command)}:\n{result.output}"
        outputs.append(result.output)

    assert "convention checks: all passed" in outputs[0]
    assert "4 rows written, 0 quarantined" in outputs[0]
    dataset = NormalizedDataset(folder / "datasets" / "mylab")
    assert len(dataset.keys) == 4  # one row per camera, as the page says
    for key in dataset.keys:
        row, image, mask = dataset.decoded(key)
        assert image.shape[:2] == (128, 128)
        # The mask is the painted head: it covers the bright pixels and leaves the black background out.
        head = image.mean(axis=-1) > 0.05
        assert 0.9 < (mask > 0.5)[head].mean() and (mask > 0.5)[~head].mean() < 0.1
    for name in ("meshes.arrow", "template.obj", "template_neck_mask.txt", "ingest_report.json"):
        assert (folder / "datasets" / "mylab" / name).is_file(), name
    assert outputs[1].rstrip().endswith("OK")
    for picture in ("sheet.png", "overlay.png"):
        assert np.asarray(Image.open(folder / picture)).ndim == 3


def test_obj_loading_advice_holds_for_ava256_topology(real_fixtures):
    """The page's OBJ advice on Ava-256's real ``face_topology.obj``: trimesh's default load merges it to
    5,779 vertices; the toolkit's reader and the recommended trimesh call keep all 7,306."""
    path = real_fixtures / "ava-256" / "face_topology.obj"
    assert len(trimesh.load(path, force="mesh").vertices) == 5779
    kept = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    assert len(kept.vertices) == len(read_obj(path)[0]) == 7306
