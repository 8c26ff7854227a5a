"""The OLAT expansion job on the sphere world: a flat-lit dataset (f00 known to stage 1, f01 held out and
fitted) relit under the four-light rig of the OLAT dataset, written as a synthetic-olat dataset.

Checks: the result validates and has the expected rows, patterns, lights, masks and provenance; the relit
OLAT images of the held-out subject follow the true OLAT images; a run resumed after an interrupted
subject, a two-worker process pool and the Ray executor write byte-identical files.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.sphere_world import LIGHTS, build_sphere_world, true_olat_image

from relightanyone.format.reader import NormalizedDataset
from relightanyone.format.shards import ShardWriter
from relightanyone.format.validate import validate_path
from relightanyone.pipelines.expand.job import expand_dataset, plan_expansion
from relightanyone.pipelines.expand.task import run_expand_task

pytestmark = pytest.mark.usefixtures("one_torch_thread")

FIT_ITERATIONS = (40, 10)
NAME = "flat-olat"


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict[str, Path]:
    return build_sphere_world(tmp_path_factory.mktemp("expand-world"), flat=True)


def _plan(world, parent: Path):
    return plan_expansion(
        world["flat"], world["stage1"], world["stage2"], parent, fit_iterations=FIT_ITERATIONS, device="cpu"
    )


def dataset_bytes(folder: Path) -> dict[str, str]:
    """sha256 of every file of a dataset folder."""
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()
    }


@pytest.fixture(scope="module")
def expanded(world, tmp_path_factory):
    parent = tmp_path_factory.mktemp("expanded")
    plan = _plan(world, parent)
    report = expand_dataset(plan, progress=False)
    return plan, report, parent / NAME


def test_the_expansion_is_a_valid_synthetic_olat_dataset_with_every_pattern(world, expanded):
    plan, report, folder = expanded
    assert [str(p) for p in validate_path(folder)] == []
    data, source = NormalizedDataset(folder), NormalizedDataset(world["flat"])
    assert data.manifest.info.kind == "synthetic-olat" and not report["up_to_date"]
    rig_patterns = [f"olat-{k:03d}" for k in range(len(LIGHTS))]
    assert data.patterns == sorted([*rig_patterns, "full"])
    assert data.subjects == ["f00", "f01"] and len(data) == 2 * 4 * (len(LIGHTS) + 1)
    assert data.lights() == NormalizedDataset(world["data"]).lights()
    assert set(data.meshes()) == {"f00/000000", "f01/000000"}
    for key in data.select(patterns="olat-002"):
        row = data.row(key)
        original = source.row(row.source)
        assert (row.camera, row.split, row.width, row.mask, row.crop) == (
            original.camera,
            original.split,
            original.width,
            original.mask,
            original.crop,
        )
        assert np.array_equal(row.K, original.K) and np.array_equal(row.w2c, original.w2c)
        assert row.source_sha256 == hashlib.sha256(original.image).hexdigest()
    parents = [p.source_dataset for p in data.manifest.info.provenance.parents]
    assert plan.inputs["stage1_checkpoint_sha256"] in parents[1]
    assert plan.inputs["stage2_checkpoint_sha256"] in parents[2]
    assert plan.inputs["source_manifest_sha256"] in parents[0]
    # f00 was a stage-1 training subject (decoded); only the held-out f01 was fitted and kept.
    assert [t["avatar"] for t in report["tasks"]] == ["decoded", "fitted"]
    assert sorted(p.name for p in (folder.parent / f"{NAME}-avatars").iterdir()) == ["f01.avatar"]
    assert expand_dataset(plan, progress=False)["up_to_date"]


@pytest.mark.parametrize(
    "subject, bound",
    [
        # Decoded from its stage-1 code: stage 2 sees this subject's own colours (a stage 2 that predicts
        # one albedo for everyone errs by 0.40 of the truth here).
        ("f00", 0.35),
        # Fitted: its albedo and the estimated scene light share an unknown colour and scale.
        ("f01", 0.6),
    ],
)
def test_relit_olat_images_follow_the_truth(expanded, subject, bound):
    _, _, folder = expanded
    data = NormalizedDataset(folder)
    errors, black, correlations = [], [], []
    for camera in range(4):
        for light in range(len(LIGHTS)):
            _, image, _ = data.decoded(f"{NAME}/{subject}/000000/cam{camera:02d}/olat-{light:03d}")
            truth, mask = true_olat_image(subject, camera, light)
            errors.append(np.abs(image - truth)[mask].mean())
            black.append(np.abs(truth)[mask].mean())
            correlations.append(np.corrcoef(image[mask].ravel(), truth[mask].ravel())[0, 1])
    # A black image errs by the mean truth; an image lit from the wrong side correlates negatively.
    assert np.mean(errors) < bound * np.mean(black), (np.mean(errors), np.mean(black))
    assert np.mean(correlations) > 0.8, correlations


def test_a_resumed_run_and_two_workers_write_the_same_bytes(world, expanded, tmp_path):
    plan, _, folder = expanded
    reference = dataset_bytes(folder)
    # An interrupted run: f00 finished, f01 left a torn temporary part, no manifest.
    resumed = _plan(world, tmp_path / "resumed")
    writer = ShardWriter(resumed.settings.output, resumed.info)
    writer.begin()
    run_expand_task(writer, resumed.settings, resumed.tasks[0])
    (writer.parts_dir / "f01.tmp").mkdir()
    (writer.parts_dir / "f01.tmp" / "images.arrow").write_bytes(b"torn")
    report = expand_dataset(resumed, progress=False)
    assert report["skipped_tasks"] == ["f00"] and [t["subject"] for t in report["tasks"]] == ["f01"]
    assert dataset_bytes(resumed.settings.output) == reference
    # The fitted avatar is reused by a run that lost its part.
    avatar = resumed.settings.avatars / "f01.avatar"
    stamp = avatar.stat().st_mtime_ns
    shutil.rmtree(resumed.settings.output)
    expand_dataset(resumed, workers=2, progress=False)
    assert avatar.stat().st_mtime_ns == stamp
    assert dataset_bytes(resumed.settings.output) == reference


@pytest.mark.ray
@pytest.mark.usefixtures("ray_exclusive")
def test_the_ray_executor_writes_the_same_bytes(world, expanded, tmp_path):
    ray = pytest.importorskip("ray", reason="the ray extra is not installed")
    _, _, folder = expanded
    plan = _plan(world, tmp_path)
    try:
        expand_dataset(plan, workers=2, executor="ray", progress=False)
    finally:
        ray.shutdown()
    assert dataset_bytes(plan.settings.output) == dataset_bytes(folder)


def test_the_command_prints_a_dry_run_plan_and_names_a_wrong_run(world, tmp_path):
    from click.testing import CliRunner

    from relightanyone.cli import cli

    args = [str(world["flat"]), "--stage1", str(world["stage1"]), "--stage2", str(world["stage2"])]
    result = CliRunner().invoke(
        cli, ["expand", *args, "--out", str(tmp_path), "--dry-run", "--subjects", "f01"]
    )
    assert result.exit_code == 0, result.output
    assert '"avatar": "fitted"' in result.output and '"images": 20' in result.output
    assert list(tmp_path.iterdir()) == []
    swapped = [str(world["flat"]), "--stage1", str(world["stage2"]), "--stage2", str(world["stage2"])]
    result = CliRunner().invoke(cli, ["expand", *swapped, "--out", str(tmp_path)])
    assert result.exit_code != 0 and "expected 'stage1'" in result.output


def test_an_expansion_exports_as_exr_files_with_its_rig(expanded, tmp_path):
    """Tools outside this one read an expansion like any normalized dataset: EXRs plus camera/light tables."""
    from click.testing import CliRunner

    from relightanyone.format.reader import NormalizedDataset
    from relightanyone.pipelines.cli import export_dataset_command

    _, _, folder = expanded
    result = CliRunner().invoke(
        export_dataset_command, [str(folder), "--format", "exr", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    dataset = NormalizedDataset(folder)
    assert len(list(tmp_path.rglob("*.exr"))) == len(dataset.select())
    lights = json.loads((tmp_path / "lights.json").read_text())
    assert [light["pattern"] for light in lights] == [row["pattern"] for row in dataset.lights()]
    assert json.loads((tmp_path / "dataset.json").read_text())["kind"] == "synthetic-olat"
