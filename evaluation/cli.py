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
    default=None,
    help="Single-stage baseline run (Table 1 compares it when given).",
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
    single_stage: Path | None,
    out: Path,
    fit_iterations: tuple[int, int],
    split: str,
    subjects: int,
    max_views: int,
    lights_subset: int,
    envmaps: int,
    views_per_step: int,
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
    inputs = EvaluationInputs(
        datasets=world_datasets(data, answers),
        stage1=stage1,
        stage2=stage2,
        single_stage=single_stage,
        answers=answers,
    )
    settings = EvaluationSettings(
        inversion_iterations=fit_iterations[0],
        finetune_iterations=fit_iterations[1],
        max_views=max_views or None,
        lights_subset=lights_subset or None,
        envmaps=envmaps or None,
        subjects_per_dataset=subjects or None,
        split=split,
        views_per_step=views_per_step,
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
