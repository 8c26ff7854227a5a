"""The colour warm-up as its own step: matrices learned into dataset views, the sources untouched."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner
from helpers.stage1_world import write_dataset

from relightanyone.cli import cli
from relightanyone.format.dataset_view import dataset_file_names, link_dataset_view
from relightanyone.format.reader import NormalizedDataset


def _listing(folder):
    return sorted(
        (p.relative_to(folder).as_posix(), p.stat().st_size) for p in folder.rglob("*") if p.is_file()
    )


def test_a_view_reads_the_same_rows_through_relative_links(tmp_path):
    source = write_dataset(tmp_path / "a" / "data", "flat", subjects=1, cameras=2, size=16)
    view = link_dataset_view(source, tmp_path / "a" / "views" / "flat")
    assert all(p.is_symlink() and not os.path.isabs(os.readlink(p)) for p in view.rglob("*") if p.is_file())
    original, seen = NormalizedDataset(source), NormalizedDataset(view)
    key = original.select()[0]
    assert seen.select() == original.select()
    np.testing.assert_array_equal(seen.decoded(key)[1], original.decoded(key)[1])
    (tmp_path / "a").rename(tmp_path / "b")  # relative links: the pipeline folder can move as a whole
    np.testing.assert_array_equal(
        NormalizedDataset(tmp_path / "b" / "views" / "flat").decoded(key)[1], seen.decoded(key)[1]
    )


def test_a_view_links_the_files_of_the_format_and_nothing_else(tmp_path):
    source = write_dataset(tmp_path / "data", "flat", subjects=1, cameras=2, size=16)
    dataset_files = sorted(p.name for p in source.iterdir())
    # What a pipeline runner or a user leaves in the folder is not part of the dataset.
    for stranger in ("_stage.json", "_stage.log", "_stage.json.x1y2.tmp", "notes.txt"):
        (source / stranger).write_text("{}")
    (source / "colour_alignment.json").write_text("{}")
    assert dataset_file_names(source) == sorted([*dataset_files, "colour_alignment.json"])
    assert {"manifest.json", "index.arrow", "images-00000.arrow", "template.obj"} <= set(dataset_files)
    view = link_dataset_view(
        source, tmp_path / "views" / "flat", exclude=frozenset({"colour_alignment.json"})
    )
    assert sorted(p.name for p in view.iterdir()) == dataset_files
    (source / "index.arrow").unlink()
    with pytest.raises(FileNotFoundError, match="index.arrow"):
        link_dataset_view(source, tmp_path / "views" / "broken")


def test_a_view_refuses_to_replace_its_source(tmp_path):
    source = write_dataset(tmp_path, "flat", subjects=1, cameras=1, size=16)
    with pytest.raises(ValueError, match="cannot replace"):
        link_dataset_view(source, source)
    with pytest.raises(FileNotFoundError, match="manifest.json"):
        link_dataset_view(tmp_path / "missing", tmp_path / "v")


def test_align_colour_writes_matrices_into_views_and_leaves_sources_alone(tmp_path):
    reference = write_dataset(tmp_path / "data", "ref", subjects=2, cameras=3, size=24, seed=1)
    cast = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.0], [0.0, 0.1, 0.7]])
    uncalibrated = write_dataset(tmp_path / "data", "cast", subjects=2, cameras=3, size=24, cast=cast, seed=2)
    before = (_listing(reference), _listing(uncalibrated))
    out = tmp_path / "aligned"
    result = CliRunner().invoke(
        cli,
        [
            "align-colour",
            "--data",
            str(reference),
            "--data",
            str(uncalibrated),
            "--uncalibrated",
            "cast",
            "--preset",
            "tiny",
            "--warmup-iterations",
            "4",
            "--eval-views",
            "1",
            "--threads",
            "1",
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    assert (_listing(reference), _listing(uncalibrated)) == before
    assert (out / "cast" / "colour_alignment.json").is_file() and not (
        out / "ref" / "colour_alignment.json"
    ).exists()
    matrix = json.loads((out / "cast" / "colour_alignment.json").read_text())["matrix"]
    assert np.isfinite(np.asarray(matrix)).all()
    report = json.loads((out / "colour_alignment.json").read_text())
    assert set(report["colour_matrices"]) == {"cast"} and report["uncalibrated"] == ["cast"]
    assert NormalizedDataset(out / "ref").select() == NormalizedDataset(reference).select()


def test_align_colour_names_an_unknown_uncalibrated_dataset(tmp_path):
    data = write_dataset(tmp_path, "ref", subjects=1, cameras=1, size=16)
    result = CliRunner().invoke(
        cli, ["align-colour", "--data", str(data), "--uncalibrated", "ava256", "--out", str(tmp_path / "o")]
    )
    assert result.exit_code != 0 and "ava256" in result.output and "ref" in result.output
