"""Checkpoints and avatar files are data: a crafted file runs no code (through every way it is opened),
older checkpoints still load and resume exactly, and no module loads a pickle that may carry code."""

from __future__ import annotations

import json
import random
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from helpers.stage1_world import tiny_stage1_preset, write_dataset

from relightanyone.cli import cli
from relightanyone.model.fit.avatar import FittedAvatar
from relightanyone.model.train.checkpoint import (
    capture_rng_state,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from relightanyone.model.train.stage1 import Stage1Config, train_stage1

REPOSITORY = Path(__file__).resolve().parents[1]


class _CreatesFile:
    """Unpickling this object opens (creates) ``path``: the proof that loading ran code."""

    def __init__(self, path: Path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def _crafted(path: Path, marker: Path) -> Path:
    """A torch archive shaped like a checkpoint whose model entry runs code when unpickled."""
    torch.save({"iteration": 0, "model": _CreatesFile(marker), "rng": {}}, path)
    return path


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("sphere-world")
    return [write_dataset(root, "da", seed=0), write_dataset(root, "db", seed=1)]


def _train(world: list[Path], out: Path, iterations: int) -> None:
    train_stage1(
        Stage1Config(world, out, tiny_stage1_preset(iterations=iterations), progress=False, evaluate=False)
    )


def test_render_stage1_refuses_a_crafted_checkpoint_without_running_it(tmp_path):
    run, marker = tmp_path / "run", tmp_path / "marker"
    run.mkdir()
    (run / "run.json").write_text(json.dumps({"stage": "stage1", "datasets": []}))
    _crafted(run / "checkpoint.pt", marker)
    result = CliRunner().invoke(
        cli, ["render", "stage1", str(run), "--subject", "s00", "--out", str(tmp_path / "out")]
    )
    assert not marker.exists(), "loading the checkpoint ran code"
    assert result.exit_code == 1, result.output
    message = result.output.strip()
    assert len(message.splitlines()) == 1 and str(run / "checkpoint.pt") in message, message
    assert "refused" in message and "io.open" in message, message


def test_training_resume_refuses_a_crafted_checkpoint_without_running_it(world, tmp_path):
    out, marker = tmp_path / "run", tmp_path / "marker"
    out.mkdir()
    _crafted(out / "checkpoint.pt", marker)
    with pytest.raises(ValueError, match=r"checkpoint\.pt: refused") as error:
        _train(world, out, iterations=8)
    assert not marker.exists(), "resuming ran code from the checkpoint"
    assert "\n" not in str(error.value)


def test_avatar_load_refuses_a_crafted_file_without_running_it(tmp_path):
    marker = tmp_path / "marker"
    torch.save({"format": "relightanyone-avatar", "gaussians": _CreatesFile(marker)}, tmp_path / "s.avatar")
    with pytest.raises(ValueError, match=r"s\.avatar: refused") as error:
        FittedAvatar.load(tmp_path / "s.avatar")
    assert not marker.exists()
    assert "\n" not in str(error.value) and "weights_only=False" not in str(error.value)


@pytest.mark.parametrize(
    "write, message",
    [
        (lambda path: path.write_bytes(b""), "not a torch file"),
        (lambda path: path.write_bytes(b"PK\x03\x04 truncated"), "unreadable training checkpoint"),
        (lambda path: torch.save({"model": {}}, path), "field 'iteration' is missing"),
    ],
)
def test_a_file_that_is_no_checkpoint_gets_a_one_line_error(tmp_path, write, message):
    write(tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match=re.escape(message)) as error:
        load_checkpoint(tmp_path / "checkpoint.pt")
    assert str(error.value).startswith(str(tmp_path / "checkpoint.pt")) and "\n" not in str(error.value)


def _old_form(state: dict) -> dict:
    """``rng`` as checkpoints of earlier versions held it: NumPy's state as a pickled ``ndarray`` tuple."""
    numpy_state = state["numpy"]
    return {
        **state,
        "numpy": (
            numpy_state["bit_generator"],
            np.asarray(numpy_state["key"], dtype=np.uint32),
            numpy_state["pos"],
            numpy_state["has_gauss"],
            numpy_state["cached_gaussian"],
        ),
    }


def test_an_older_checkpoint_still_loads_and_resumes_to_the_same_weights(world, tmp_path):
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    _train(world, reference, iterations=8)
    _train(world, resumed, iterations=4)
    checkpoint = load_checkpoint(resumed / "checkpoint.pt")
    # Rewritten as an earlier version wrote it, with NumPy's generator somewhere else than at the save.
    old = {**checkpoint, "rng": _old_form(checkpoint["rng"])}
    torch.save(old, resumed / "checkpoint.pt")
    np.random.seed(1234)
    random.seed(1234)
    _train(world, resumed, iterations=8)
    expected, got = load_checkpoint(reference / "checkpoint.pt"), load_checkpoint(resumed / "checkpoint.pt")
    assert got["iteration"] == expected["iteration"] == 8
    for name, tensor in expected["model"].items():
        assert torch.equal(tensor, got["model"][name]), name
    assert got["rng"]["numpy"] == expected["rng"]["numpy"]


def test_the_numpy_random_state_round_trips_through_both_forms(tmp_path):
    np.random.seed(7)
    np.random.normal()  # a cached Gaussian is part of the state
    payload = {"iteration": 1, "model": {}, "optimizer": {}, "preset": {}, "subjects": [], "seed": 0}
    state = capture_rng_state()
    expected = np.random.normal(size=4)
    save_checkpoint(tmp_path / "new.pt", {**payload, "rng": state})
    torch.save({**payload, "rng": _old_form(state)}, tmp_path / "old.pt")
    for name in ("new.pt", "old.pt"):
        restore_rng_state(load_checkpoint(tmp_path / name)["rng"])
        assert np.array_equal(np.random.normal(size=4), expected), name


@pytest.mark.parametrize(
    "array", [np.zeros(3), np.array([1, "x"], dtype=object), np.zeros((2, 2), np.uint32)]
)
def test_an_older_checkpoint_with_any_other_numpy_array_is_refused(tmp_path, array):
    payload = {"iteration": 1, "model": {}, "optimizer": {}, "preset": {}, "subjects": [], "seed": 0}
    torch.save({**payload, "rng": {"numpy": ("MT19937", array, 0, 0, 0.0)}}, tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match="refused"):
        load_checkpoint(tmp_path / "checkpoint.pt")


def test_no_module_loads_a_pickle_that_may_carry_code():
    """Every ``torch.load`` passes ``weights_only=True``; nothing calls pickle, ``weights_only=False`` or
    ``allow_pickle=True`` (tests excepted: they write crafted files)."""
    unsafe = re.compile(
        r"weights_only\s*=\s*False|allow_pickle\s*=\s*True|pickle\.loads?\(|\bdill\b|joblib\.load"
    )
    findings = []
    for path in sorted(REPOSITORY.rglob("*.py")):
        relative = path.relative_to(REPOSITORY)
        if relative.parts[0] in (".venv", "tests", "build") or relative.parts[0].startswith("."):
            continue
        text = path.read_text("utf-8")
        findings += [f"{relative}: {m.group(0)}" for m in unsafe.finditer(text)]
        for call in re.finditer(r"torch\.load\(([^()]*(?:\([^()]*\)[^()]*)*)\)", text):
            if not re.search(r"weights_only\s*=\s*True", call.group(1)):
                findings.append(f"{relative}: {call.group(0)}")
    assert not findings, findings
