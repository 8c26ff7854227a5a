"""The world orchestrator and CLI: determinism, dataset independence, bad parameters, contact sheet."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import pytest
from click.testing import CliRunner

from relightanyone.cli import cli
from relightanyone.synth.cli import COMMANDS
from relightanyone.synth.presets import DatasetSize, get_preset
from relightanyone.synth.world import generate_world


def nano_preset():
    """The smallest world that still exercises every codec (AVIF, DNG, mp4, EXR)."""
    tiny = get_preset("tiny")
    return replace(
        tiny,
        name="nano",
        template_segments=24,
        texture_size=32,
        answer_lights=2,
        envmap_count=1,
        d1=replace(tiny.d1, train_subjects=1, test_subjects=1, cameras=2, image_size=(32, 48)),
        d2=DatasetSize(train_subjects=1, test_subjects=1, cameras=2, image_size=(32, 48), frames=2, lights=6),
        d3=DatasetSize(train_subjects=1, test_subjects=1, cameras=8, image_size=(32, 24), lights=4),
        d4=DatasetSize(train_subjects=1, test_subjects=1, cameras=3, image_size=(32, 48), frames=2, lights=8),
    )


def tree_hashes(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def nano_world(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("nano") / "world"
    generate_world(out, nano_preset(), seed=11, datasets=("d1", "d2", "d3", "d4"), progress=False)
    return out


def test_same_seed_gives_the_same_bytes_whatever_other_datasets_are_made(nano_world, tmp_path):
    again = tmp_path / "again"  # asked in another order, made by two processes
    generate_world(
        again, nano_preset(), seed=11, datasets=("d4", "d2", "d3", "d1"), progress=False, workers=2
    )
    assert tree_hashes(again) == tree_hashes(nano_world)
    alone = tmp_path / "alone"
    generate_world(alone, nano_preset(), seed=11, datasets=("d3",), progress=False)
    first = tree_hashes(nano_world)
    for path, digest in tree_hashes(alone).items():
        if path not in ("world.json", "answers/splits.json"):
            assert first[path] == digest, path


def test_another_seed_changes_the_world(nano_world, tmp_path):
    other = tmp_path / "other"
    generate_world(other, nano_preset(), seed=12, datasets=("d3",), progress=False)
    first = tree_hashes(nano_world)
    changed = [p for p, d in tree_hashes(other).items() if p.startswith("stereo_rig/") and first.get(p) != d]
    assert changed


def test_world_json_lists_what_was_written(nano_world):
    world = json.loads((nano_world / "world.json").read_text())
    assert world["datasets"] == ["d1", "d2", "d3", "d4"] and world["seed"] == 11 and world["preset"] == "nano"
    for dataset, folder in world["native_dirs"].items():
        assert (nano_world / folder).is_dir()
        assert (nano_world / "tracking" / dataset).is_dir()
        assert (nano_world / "answers" / dataset / "truth.json").is_file()
    assert (nano_world / "answers" / "template" / "template.obj").is_file()


@pytest.mark.parametrize(
    "change, message",
    [
        ({"datasets": ("d5",)}, "unknown dataset"),
        ({"datasets": ()}, "no dataset"),
        ({"preset": "huge"}, "unknown preset"),
        ({"d2": DatasetSize(1, 1, cameras=0, image_size=(32, 48))}, "at least one camera"),
        ({"d2": DatasetSize(1, 1, cameras=2, image_size=(0, 48))}, "image_size"),
        ({"d2": DatasetSize(0, 0, cameras=2, image_size=(32, 48))}, "at least one subject"),
        ({"d3": DatasetSize(1, 1, cameras=8, image_size=(33, 24), lights=4)}, "even"),
        ({"answer_lights": 0}, "answer_lights"),
    ],
)
def test_bad_parameters_are_refused_before_writing(tmp_path, change, message):
    datasets = change.pop("datasets", ("d2", "d3"))
    preset = change.pop("preset", None) or replace(nano_preset(), **change)
    out = tmp_path / "world"
    with pytest.raises(ValueError, match=message):
        generate_world(out, preset, datasets=datasets, progress=False)
    assert not out.exists() or not any(out.iterdir())


def test_non_empty_output_needs_overwrite_and_overwrite_spares_foreign_folders(tmp_path):
    out = tmp_path / "world"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        generate_world(out, nano_preset(), datasets=("d3",), progress=False)
    with pytest.raises(ValueError, match="not part of a synthetic world"):
        generate_world(out, nano_preset(), datasets=("d3",), progress=False, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine"


def test_cli_refuses_bad_datasets_and_previews_a_world(nano_world, tmp_path):
    runner = CliRunner()
    result = runner.invoke(COMMANDS["synth"], ["--out", str(tmp_path / "w"), "--datasets", "d2,d9"])
    assert result.exit_code != 0 and "d9" in result.output
    result = runner.invoke(cli, ["synth", "--out", str(nano_world), "--datasets", "d3"])
    assert result.exit_code != 0 and "--overwrite" in result.output
    sheet = tmp_path / "sheet.png"
    result = runner.invoke(COMMANDS["synth-preview"], [str(nano_world), "--out", str(sheet)])
    assert result.exit_code == 0, result.output
    from PIL import Image

    image = Image.open(sheet)
    assert image.size[1] >= 4 * 192  # one row per dataset
    result = runner.invoke(cli, ["synth-preview", str(tmp_path), "--out", str(sheet)])
    assert result.exit_code != 0 and "world.json" in result.output


def test_training_subjects_are_rendered_like_the_held_out_answers(nano_world):
    """The evaluation renders training subjects' OLAT truth on demand; for a held-out subject the same
    function reproduces the answers on disk, so both come from the same people and lights."""
    import numpy as np

    from relightanyone.evaluation.truth import WorldAnswers, read_answer_image
    from relightanyone.synth.world import render_subject_olat

    answers = WorldAnswers(nano_world)
    held_out = answers.subjects_in("d2", "test")[0]
    camera = sorted(answers.cameras("d2"))[0]
    rendered = render_subject_olat(nano_world, "d2", held_out, [camera], preset=nano_preset())[camera]
    for light in range(len(rendered)):
        on_disk = read_answer_image(answers.olat_path("d2", held_out, camera, light))
        np.testing.assert_allclose(rendered[light], on_disk, rtol=2e-3, atol=2e-3)  # answers are half floats
    training = next(s for s, split in answers.splits["d2"].items() if split == "train")
    other = render_subject_olat(nano_world, "d2", training, [camera], preset=nano_preset())[camera]
    assert other.shape == rendered.shape and not np.allclose(other, rendered)
    with pytest.raises(ValueError, match="pass the world's preset"):
        render_subject_olat(nano_world, "d2", training, [camera])
    with pytest.raises(ValueError, match="no subject"):
        render_subject_olat(nano_world, "d2", "nobody", [camera], preset=nano_preset())


def test_splits_are_published_with_validation_subjects_and_answers(tmp_path):
    """Train, then validation, then test subjects; the protocol file and the answers list all three, and
    validation subjects get answers like test subjects (model selection compares against them)."""
    preset = nano_preset()
    preset = replace(preset, d3=replace(preset.d3, train_subjects=1, val_subjects=1, test_subjects=1))
    generate_world(tmp_path / "w", preset, seed=3, datasets=("d3",), progress=False)
    published = json.loads((tmp_path / "w" / "splits" / "stereo_rig.json").read_text())
    assert sorted(published.values()) == ["test", "train", "val"]
    assert json.loads((tmp_path / "w" / "answers" / "splits.json").read_text()) == {"d3": published}
    for subject, split in published.items():
        answered = (tmp_path / "w" / "answers" / "d3" / "olat" / subject).is_dir()
        assert answered == (split != "train"), subject
