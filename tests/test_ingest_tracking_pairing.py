"""Tracking that matches the capture: VHAP timesteps paired with native video frames from evidence (or a
stop naming the cause), VHAP's parameter-mode export and a template without its neck mask refused before
anything is written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from helpers.custom_capture import make_capture
from helpers.small_worlds import make_world, reduced_preset

from relightanyone.cli import cli
from relightanyone.format.reader import NormalizedDataset
from relightanyone.ingest import nersemble
from relightanyone.ingest.records import AdapterOptions
from relightanyone.ingest.runner import ingest_dataset, prepare
from relightanyone.ingest.tracking import TrackingMismatchError, TrackingOptions, timestep_mapping
from relightanyone.synth.presets import DatasetSize
from relightanyone.synth.truth import DatasetTruth

VIDEO_FPS = 73
NATIVE_FRAMES = 7
TRACKED = (0, 3, 6)  # what VHAP's 25 fps extraction keeps of a 7-frame 73 fps video: round(k * 73 / 25)
SMALL = reduced_preset(
    d4=DatasetSize(
        train_subjects=1, test_subjects=0, cameras=3, image_size=(40, 56), frames=NATIVE_FRAMES, lights=4
    )
)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("world_pairing"), SMALL, seed=3, datasets=("d4",))


def tracking_at_25_fps(world: Path, out: Path, fps_key: bool = False) -> Path:
    """The world's VHAP export as VHAP's 25 fps flow writes it: timestep k is native frame round(2.92 k),
    and ``timestep_index_original`` counts the extracted frames."""
    for source in sorted((world / "tracking" / "d4").iterdir()):
        target = out / source.name
        (target / "meshes").mkdir(parents=True)
        document = json.loads((source / "transforms.json").read_text())
        frames = []
        for k, native in enumerate(TRACKED):
            shutil.copy(source / "meshes" / f"{native:05d}.obj", target / "meshes" / f"{k:05d}.obj")
            for entry in document["frames"]:
                if entry["timestep_index_original"] == native:
                    frames.append(
                        {
                            **entry,
                            "timestep_index": k,
                            "timestep_index_original": k,
                            "timestep_id": f"{k:06d}",
                            "mesh_path": f"meshes/{k:05d}.obj",
                        }
                    )
        shutil.copy(source / "canonical.obj", target / "canonical.obj")
        document = {"frames": frames, "timestep_indices": list(range(len(TRACKED)))}
        if fps_key:
            document["fps"] = 25
        (target / "transforms.json").write_text(json.dumps(document))
    return out


def template(world: Path) -> Path:
    return world / "answers" / "template" / "template.obj"


def test_ambiguous_pairing_stops_naming_the_flag(world, tmp_path):
    tracking = tracking_at_25_fps(world, tmp_path / "tracking")
    out = tmp_path / "out"
    args = ["ingest", "nersemble", str(world / "nersemble"), "--tracking", str(tracking), "--out", str(out),
            "--preset", "tiny", "--template", str(template(world))]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1
    assert "cannot tell how the tracked timesteps pair with the 73 fps video" in result.output
    assert "--tracking-fps 25" in result.output and not out.exists()


@pytest.mark.parametrize("stated", ["flag", "export"])
def test_25_fps_tracking_is_paired_with_the_right_native_frames(world, tmp_path, stated):
    tracking = tracking_at_25_fps(world, tmp_path / "tracking", fps_key=stated == "export")
    options = TrackingOptions(tracking_fps=25.0 if stated == "flag" else None)
    plan = nersemble.plan(world / "nersemble", AdapterOptions())
    assert plan.subjects[0].frame_rate == VIDEO_FPS and plan.subjects[0].frame_count == NATIVE_FRAMES
    summary = ingest_dataset(
        plan,
        tracking,
        tmp_path / "out",
        "tiny",
        progress=False,
        template=template(world),
        tracking_options=options,
    )
    assert summary.rows == 3 * len(TRACKED) and summary.quarantined == 3 * (NATIVE_FRAMES - len(TRACKED))
    truth = DatasetTruth.load(world / "answers" / "d4" / "truth.json")
    dataset = NormalizedDataset(summary.path)
    assert sorted({dataset.row(k).frame for k in dataset.keys}) == list(TRACKED)
    for key in dataset.keys:
        row = dataset.row(key)
        expected = truth.cameras[row.camera].w2c @ truth.head_poses[(row.subject, row.frame)]
        centre_error = np.linalg.norm(
            row.w2c[:3, :3].T @ row.w2c[:3, 3] - expected[:3, :3].T @ expected[:3, 3]
        )
        assert centre_error < 3e-3, (key, centre_error)  # mispairing is off by centimetres
    untracked = [e for e in dataset.quarantine() if e.item.endswith("/full")]
    assert untracked and all("not tracked" in e.reason and "0, 3, 6" in e.reason for e in untracked)
    report = json.loads((summary.path / "ingest_report.json").read_text())
    (pairing,) = {s["frame_pairing"] for s in report["alignment"]["subjects"].values()}
    assert "25 fps tracking" in pairing and "73 fps video" in pairing


def test_a_stated_rate_that_does_not_fit_the_video_stops(world, tmp_path):
    tracking = tracking_at_25_fps(world, tmp_path / "tracking")
    plan = nersemble.plan(world / "nersemble", AdapterOptions())
    with pytest.raises(TrackingMismatchError, match="past the video's 7 frames"):
        prepare(plan, tracking, "tiny", template(world), tracking_options=TrackingOptions(tracking_fps=10.0))


def test_every_frame_tracked_pairs_one_to_one(world, tmp_path):
    plan = nersemble.plan(world / "nersemble", AdapterOptions())
    _, _, tasks = prepare(plan, world / "tracking" / "d4", "tiny", template(world))
    assert len(tasks[0].alignments) == NATIVE_FRAMES and "native frame numbers" in tasks[0].frame_pairing


def test_parameter_mode_export_is_refused_before_anything_is_written(world, tmp_path):
    tracking = tmp_path / "tracking"
    shutil.copytree(world / "tracking" / "d4", tracking)
    for subject in tracking.iterdir():
        shutil.rmtree(subject / "meshes")
        (subject / "flame_param").mkdir()
        np.savez(subject / "flame_param" / "00000.npz", expr=np.zeros((1, 100)))
    out = tmp_path / "out"
    args = ["ingest", "nersemble", str(world / "nersemble"), "--tracking", str(tracking), "--out", str(out),
            "--preset", "tiny", "--template", str(template(world)), "--dry-run"]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1 and "parameter mode" in result.output
    assert "--flame-mode mesh" in result.output and not out.exists()


def test_template_without_neck_mask_needs_an_explicit_opt_out(tmp_path):
    capture = make_capture(tmp_path / "capture")
    (capture / "neck_mask.txt").unlink()
    out = tmp_path / "out"
    args = ["ingest", "custom", str(capture), "--out", str(out), "--preset", "tiny"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1 and "no neck mask" in result.output and "--no-neck-mask" in result.output
    assert not out.exists()
    result = CliRunner().invoke(cli, [*args, "--no-neck-mask"])
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "custom" / "manifest.json").read_text())
    assert "no neck mask" in manifest["provenance"]["template"]


@pytest.mark.parametrize(
    ("timesteps", "fps", "rate", "count", "native_of_last", "error"),
    [
        ([10, 14], None, None, None, 14, None),  # still images: native frame numbers
        ([10, 14], 25.0, None, None, 14, None),  # a stated rate has no video to apply to
        ([0, 1, 2, 299], None, 73.0, 300, 299, None),  # past a 25 fps extraction's end: native frames
        ([0, 1, 2], None, 73.0, 300, None, "cannot tell"),  # both readings fit
        ([0, 1, 102], 25.0, 73.0, 300, 298, None),  # round(102 * 2.92) = 298
        ([0, 1, 103], 25.0, 73.0, 300, None, "past the video's 300 frames"),
        ([0, 400], None, 73.0, 300, None, "past the video's 300 frames"),
        ([0, 1], 100.0, 73.0, 300, None, "faster than"),
    ],
)
def test_timestep_mapping_rules(timesteps, fps, rate, count, native_of_last, error):
    options = TrackingOptions(tracking_fps=fps)
    if error:
        with pytest.raises(TrackingMismatchError, match=error):
            timestep_mapping(timesteps, None, rate, count, options, "transforms.json")
    else:
        mapping = timestep_mapping(timesteps, None, rate, count, options, "transforms.json")
        assert mapping.native(timesteps[-1]) == native_of_last


def changed_template(world: Path, folder: Path, change: str) -> Path:
    """The world's template (and neck mask) rewritten in ``folder``: in mm, in a shuffled vertex order, or
    moved 10 cm, as a user's template may disagree with the tracking's own ``canonical.obj``."""
    from relightanyone.ingest.tracking import load_template
    from relightanyone.synth.template import write_obj

    loaded = load_template(template(world))
    vertices, faces, neck = loaded.vertices, loaded.faces, loaded.neck_vertices
    if change == "mm":
        vertices = vertices * 1000.0
    elif change == "order":
        order = np.random.default_rng(0).permutation(len(vertices))  # new vertex i is old order[i]
        inverse = np.argsort(order)
        vertices, faces, neck = vertices[order], inverse[faces], neck[order]
    else:
        vertices = vertices + [0.0, 0.10, 0.0]
    folder.mkdir(parents=True)
    write_obj(folder / "template.obj", vertices, faces)
    (folder / "neck_mask.txt").write_text("".join(f"{int(v)}\n" for v in neck))
    return folder / "template.obj"


@pytest.mark.parametrize(
    "change, words",
    [
        ("mm", "about 1000x larger: in mm?"),
        ("order", "another vertex order or topology"),
        ("frame", "the template is in another frame"),
    ],
)
def test_template_that_disagrees_with_the_exports_shape_stops(world, tmp_path, change, words):
    """The frames are fitted to the export's ``canonical.obj``, so the template is compared with it."""
    assert any((p / "canonical.obj").is_file() for p in (world / "tracking" / "d4").iterdir())
    path = changed_template(world, tmp_path / "template", change)
    out = tmp_path / "out"
    args = ["ingest", "nersemble", str(world / "nersemble"), "--tracking", str(world / "tracking" / "d4"),
            "--out", str(out), "--preset", "tiny", "--template", str(path)]  # fmt: skip
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1, result.output
    finding = next(line for line in result.output.splitlines() if "check fit-residual" in line)
    assert words in finding and "canonical.obj" in finding and str(path) in finding
    assert not out.exists()
    # The template the world ships passes.
    args[-1] = str(template(world))
    clean = CliRunner().invoke(cli, [*args, "--dry-run"])
    assert clean.exit_code == 0 and "convention checks: all passed" in clean.output, clean.output


def test_sequence_is_chosen_by_name_or_short_name_and_several_need_a_choice(tmp_path):
    from relightanyone.ingest.nersemble import choose_sequence

    for name in ("EMO-1-shout+laugh", "EXP-1-head", "EXP-10-neck", "BACKGROUND"):
        (tmp_path / "sequences" / name / "images").mkdir(parents=True)
        (tmp_path / "sequences" / name / "images" / "cam_220700191.mp4").write_bytes(b"")
    (tmp_path / "sequences" / "EMPTY-1" / "images").mkdir(parents=True)  # no video: not a choice
    assert choose_sequence(tmp_path, "v2", "EMO-1") == ("EMO-1-shout+laugh", "")
    assert choose_sequence(tmp_path, "v2", "EXP-1-head") == ("EXP-1-head", "")
    chosen, why = choose_sequence(tmp_path, "v2", None)
    assert chosen is None and "3 sequences hold images" in why and "--sequence NAME" in why
    chosen, why = choose_sequence(tmp_path, "v2", "SEN-1")
    assert chosen is None and why.startswith("no sequence SEN-1 with images (sequences: EMO-1-shout+laugh")
    for name in ("EXP-1-head", "EXP-10-neck"):
        (tmp_path / "sequences" / name / "images" / "cam_220700191.mp4").unlink()
    assert choose_sequence(tmp_path, "v2", None) == ("EMO-1-shout+laugh", "")
