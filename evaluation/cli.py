"""``relightanyone evaluate``: the paper's evaluation on a synthetic world's held-out subjects.

Only click is imported at module level; the model (torch) loads inside the command, so that
``relightanyone --help`` stays instant.
"""

from __future__ import annotations

from pathlib import Path

import click

from relightanyone.cli_options import (
    EXISTING_FOLDER,
    FILE,
    device_option,
    fit_iterations_option,
    out_option,
    quiet_option,
    seed_option,
)


@click.command("evaluate")
@click.option(
    "--world",
    type=EXISTING_FOLDER,
    required=True,
    help="Synthetic world folder (its answers/ hold the truth; ingest never reads them).",
)
@click.option(
    "--data",
    "data",
    multiple=True,
    required=True,
    metavar="NAME=DIR",
    help="Normalized dataset and the world dataset it came from (d1..d4), e.g. d1=norm/faceolat; "
    "a bare DIR is matched to the world dataset by its cameras. Repeat per dataset.",
)
@click.option("--stage1", type=EXISTING_FOLDER, required=True)
@click.option("--stage2", type=EXISTING_FOLDER, required=True)
@click.option(
    "--single-stage",
    "single_stage",
    type=EXISTING_FOLDER,
    multiple=True,
    help="Single-stage baseline run (Table 1 compares it when given). Repeat for its loss variants: the "
    "one with the best OLAT relighting of the OLAT dataset's validation subjects is the baseline.",
)
@click.option(
    "--ablation",
    "ablation",
    multiple=True,
    type=(click.Choice(["with-zl", "no-zl", "colour-matrix"]), EXISTING_FOLDER, EXISTING_FOLDER),
    metavar="ARM STAGE1 STAGE2",
    help="A lighting-code ablation arm and its stage-1 and stage-2 runs (repeat per arm): with-zl (the "
    "method; default: --stage1/--stage2), no-zl (stage 1 trained --no-lighting-code), colour-matrix (no "
    "lighting codes, datasets aligned by learned 3x3 matrices). Table 3 compares them.",
)
@click.option(
    "--ablation-fits/--no-ablation-fits",
    default=True,
    show_default=True,
    help="Table 3b fits the held-out flat-lit subjects with every arm (off: with the main runs only).",
)
@click.option(
    "--flat-fits-with-dataset-code/--flat-fits-with-unknown-light",
    "flat_fits_with_dataset_code",
    default=True,
    show_default=True,
    help="Table 3b renders a held-out flat-lit subject's input views under its dataset's stage-1 lighting "
    "code, as stage 1 saw that dataset (off: as a capture under an unknown light of the OLAT rig).",
)
@click.option(
    "--unknown-lighting/--dataset-lighting",
    "unknown_lighting",
    default=True,
    show_default=True,
    help="Fit Table 1/2 subjects on the world's renders under a lighting unknown to the fit (off: on the "
    "dataset's full-on rows, lit by the calibrated rig the fit's prior starts from).",
)
@click.option(
    "--monocular-single-image/--calibrated-single-image",
    "monocular_single_image",
    default=True,
    show_default=True,
    help="Table 2's single-image fit gets what one image yields: a monocular-quality mesh, a mask from "
    "the image, a generic focal length (off: the dataset's tracked mesh, mask and calibration).",
)
@out_option("Output folder.")
@fit_iterations_option((100, 100), "Inversion and finetuning iterations of every fit.")
@click.option(
    "--split",
    type=click.Choice(["test", "val"]),
    default="test",
    show_default=True,
    help="Held-out split scored: test (the reported numbers) or val (model selection and tuning). "
    "Subjects any run trained on are refused.",
)
@click.option(
    "--subjects",
    type=click.IntRange(min=0),
    default=1,
    show_default=True,
    help="Held-out subjects per dataset (0: all).",
)
@click.option(
    "--max-views",
    type=click.IntRange(min=0),
    default=8,
    show_default=True,
    help="Cameras per fit and comparison (0: all).",
)
@click.option(
    "--lights-subset",
    type=click.IntRange(min=0),
    default=16,
    show_default=True,
    help="OLAT lights compared (0: all).",
)
@click.option(
    "--envmaps",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="Environment maps compared (0: all).",
)
@click.option("--views-per-step", type=int, default=4, show_default=True)
@click.option(
    "--lighting-prior-weight",
    type=click.FloatRange(min=0),
    default=1.0,
    show_default=True,
    help="λ_I of every fit: the pull of the fitted light toward the training rig's full-on light (choose "
    "it with --split val, never on test subjects).",
)
@seed_option()
@click.option(
    "--json-copy",
    type=FILE,
    default=None,
    help="Also copy evaluation.json here (e.g. bench/results/evaluation.json).",
)
@quiet_option()
@device_option()
def evaluate_command(
    world: Path,
    data: tuple[str, ...],
    stage1: Path,
    stage2: Path,
    single_stage: tuple[Path, ...],
    ablation: tuple[tuple[str, Path, Path], ...],
    ablation_fits: bool,
    flat_fits_with_dataset_code: bool,
    unknown_lighting: bool,
    monocular_single_image: bool,
    out: Path,
    fit_iterations: tuple[int, int],
    split: str,
    subjects: int,
    max_views: int,
    lights_subset: int,
    envmaps: int,
    views_per_step: int,
    lighting_prior_weight: float,
    seed: int,
    json_copy: Path | None,
    quiet: bool,
    device: str,
) -> None:
    """Fit held-out subjects and measure relighting against the synthetic world's answers.

    Writes OUT/report.md (tables next to the paper's numbers, image grids), OUT/evaluation.json and
    OUT/grids/*.png.
    """
    from relightanyone.evaluation.run import run_evaluation, world_datasets
    from relightanyone.evaluation.tables import EvaluationInputs, EvaluationSettings
    from relightanyone.evaluation.truth import WorldAnswers
    from relightanyone.model.device import resolve_device

    answers = WorldAnswers(world)
    arms: dict[str, tuple[Path, Path]] = {}
    for arm, arm_stage1, arm_stage2 in ablation:
        if arm in arms:
            raise click.UsageError(f"--ablation {arm} given twice")
        arms[arm] = (arm_stage1, arm_stage2)
    inputs = EvaluationInputs(
        datasets=world_datasets(data, answers),
        stage1=stage1,
        stage2=stage2,
        single_stage=single_stage[0] if single_stage else None,
        single_stage_variants=tuple(single_stage[1:]),
        answers=answers,
        ablation=arms,
    )
    settings = EvaluationSettings(
        inversion_iterations=fit_iterations[0],
        finetune_iterations=fit_iterations[1],
        max_views=max_views or None,
        lights_subset=lights_subset or None,
        envmaps=envmaps or None,
        subjects_per_dataset=subjects or None,
        ablation_fits=ablation_fits,
        flat_fits_with_dataset_code=flat_fits_with_dataset_code,
        unknown_lighting=unknown_lighting,
        monocular_single_image=monocular_single_image,
        split=split,
        views_per_step=views_per_step,
        lighting_prior_weight=lighting_prior_weight,
        seed=seed,
        progress=not quiet,
        device=str(resolve_device(device)),
    )
    results = run_evaluation(inputs, settings, out, json_copy)
    click.echo(
        f"wrote {out / 'report.md'} and {out / 'evaluation.json'} ({results['run_kind']}, "
        f"protocol {results['protocol_sha256'][:12]})"
    )
    for claim, value in results.get("goals", {}).items():
        click.echo(f"  {claim}: {'not evaluated' if value is None else ('yes' if value else 'NO')}")


COMMANDS: dict[str, click.Command] = {"evaluate": evaluate_command}
