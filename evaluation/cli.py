"""``relightanyone evaluate``: the paper's evaluation on a synthetic world's held-out subjects.

Only click is imported at module level; the model loads inside the command.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import click


def parse_data_options(values: tuple[str, ...], world: Path | None) -> dict[str, Path]:
    """``NAME=DIR`` (NAME = the world's dataset folder, d1..d4) or a bare ``DIR`` matched by its cameras."""
    datasets: dict[str, Path] = {}
    answers = None
    for value in values:
        name, sep, folder = value.partition("=")
        if sep:
            path = Path(folder)
        else:
            from relightanyone.evaluation.truth import WorldAnswers, match_world_dataset
            from relightanyone.format.reader import NormalizedDataset

            if world is None:
                raise click.BadParameter(f"{value}: without --world, write NAME=DIR (e.g. d1={value})")
            answers = answers or WorldAnswers(world)
            path = Path(value)
            name = match_world_dataset(answers, set(NormalizedDataset(path).cameras), str(path))
        if not (path / "manifest.json").is_file():
            raise click.BadParameter(f"{path}: not a normalized dataset (no manifest.json)")
        if name in datasets:
            raise click.BadParameter(f"world dataset {name!r} given twice (--data)")
        datasets[name] = path
    return datasets


def run_evaluation(inputs, settings, out: Path, json_copy: Path | None = None) -> dict:
    """Run every table, write ``out/report.md``, ``out/evaluation.json``, ``out/grids/``; returns results."""
    from dataclasses import asdict

    from relightanyone.evaluation.report import write_report
    from relightanyone.evaluation.tables import Evaluation

    evaluation = Evaluation(inputs, settings)
    results = evaluation.run()
    results["settings"] = asdict(settings)
    results["inputs"] = {
        "world": None if inputs.answers is None else str(inputs.answers.world),
        "datasets": {k: str(v) for k, v in inputs.datasets.items()},
        "stage1": str(inputs.stage1),
        "stage2": str(inputs.stage2),
        "single_stage": None if inputs.single_stage is None else str(inputs.single_stage),
    }
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_report(out, results, evaluation.tables, evaluation.inputs_images)
    if json_copy is not None:
        Path(json_copy).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "evaluation.json", json_copy)
    return results


@click.command("evaluate")
@click.option(
    "--world",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
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
@click.option("--stage1", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True)
@click.option("--stage2", type=click.Path(exists=True, file_okay=False, path_type=Path), required=True)
@click.option(
    "--single-stage",
    "single_stage",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    default=None,
    help="Single-stage baseline run (Table 1 compares it when given).",
)
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True, help="Output folder.")
@click.option(
    "--fit-iterations",
    nargs=2,
    type=int,
    default=(100, 100),
    show_default=True,
    metavar="N M",
    help="Inversion and finetuning iterations of every fit.",
)
@click.option(
    "--subjects", type=int, default=1, show_default=True, help="Held-out subjects per dataset (0: all)."
)
@click.option(
    "--max-views", type=int, default=8, show_default=True, help="Cameras per fit and comparison (0: all)."
)
@click.option(
    "--lights-subset", type=int, default=16, show_default=True, help="OLAT lights compared (0: all)."
)
@click.option("--envmaps", type=int, default=0, show_default=True, help="Environment maps compared (0: all).")
@click.option("--views-per-step", type=int, default=4, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option(
    "--json-copy",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Also copy evaluation.json here (e.g. bench/results/evaluation.json).",
)
@click.option("--quiet", is_flag=True, help="No progress bars.")
def evaluate_command(
    world: Path,
    data: tuple[str, ...],
    stage1: Path,
    stage2: Path,
    single_stage: Path | None,
    out: Path,
    fit_iterations: tuple[int, int],
    subjects: int,
    max_views: int,
    lights_subset: int,
    envmaps: int,
    views_per_step: int,
    seed: int,
    json_copy: Path | None,
    quiet: bool,
) -> None:
    """Fit held-out subjects and measure relighting against the synthetic world's answers.

    Writes OUT/report.md (tables next to the paper's numbers, image grids), OUT/evaluation.json and
    OUT/grids/*.png.
    """
    from relightanyone.evaluation.tables import EvaluationInputs, EvaluationSettings
    from relightanyone.evaluation.truth import WorldAnswers

    for name, value in (
        ("--subjects", subjects),
        ("--max-views", max_views),
        ("--lights-subset", lights_subset),
        ("--envmaps", envmaps),
    ):
        if value < 0:
            raise click.BadParameter(f"{name} must be >= 0 (0 means all), got {value}")
    if min(fit_iterations) < 0:
        raise click.BadParameter(f"--fit-iterations must be >= 0, got {fit_iterations}")
    try:
        answers = WorldAnswers(world)
        inputs = EvaluationInputs(
            datasets=parse_data_options(data, world),
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
            views_per_step=views_per_step,
            seed=seed,
            progress=not quiet,
        )
        results = run_evaluation(inputs, settings, out, json_copy)
    except (FileNotFoundError, ValueError) as error:
        raise click.ClickException(str(error)) from error
    click.echo(f"wrote {out / 'report.md'} and {out / 'evaluation.json'}")
    for claim, value in results.get("goals", {}).items():
        click.echo(f"  {claim}: {'not evaluated' if value is None else ('yes' if value else 'NO')}")


COMMANDS: dict[str, click.Command] = {"evaluate": evaluate_command}
