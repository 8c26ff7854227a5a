"""The staged DAG: stages, their dependencies, ``_stage.json`` records, planning and execution.

A stage runs one command (a ``relightanyone`` sub-command or any executable) that reads its ``inputs``
and writes its one ``output`` directory. Stage B depends on stage A when one of B's inputs is A's output,
lies inside it or contains it (a folder holding several stages' outputs), and when B lists A in
``after:``. Outputs of two stages may not overlap.

After a stage's command succeeds, the runner writes ``<output>/_stage.json`` atomically: its config
(kind, arguments, environment), the fingerprint of every input, the package version, the hashes of the
output files, start and end time. A stage is skipped when that record exists, its fingerprint (config +
input digests + package version) is unchanged and its output files still hash to the recorded digest.
Before a stage runs, its old record is deleted first, so a run interrupted at any point (even by SIGKILL)
leaves no record and the stage runs again next time. Stage commands resume their own partial work (a
training checkpoint, an ingest's finished subjects, existing avatars), which is right only for work of the
same config and inputs: an output left by a completed run (the stage runs again because something
changed, or ``--force``) or by an unfinished run of another fingerprint (``attempt_path``) is removed
before the command starts, and only an unfinished run of the same fingerprint is resumed.
"""

from __future__ import annotations

import datetime
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from relightanyone.errors import RelightAnyoneError
from relightanyone.locking import output_lock
from relightanyone.pipelines.dag.fingerprint import (
    Fingerprint,
    HashCache,
    compare_listings,
    fingerprint_path,
    listing_to_json,
)
from relightanyone.pipelines.dag.pipeline_file import PipelineError, PipelineSpec, StageSpec, parse_pipeline
from relightanyone.pipelines.dag.process import run_with_log, stage_argv
from relightanyone.pipelines.dag.record import (
    RECORD_FORMAT,
    STAGE_LOG_NAME,
    STAGE_RECORD_NAME,
    attempt_path,
    live_log_path,
    package_version,
    read_attempt,
    read_record,
    stage_config,
    stage_fingerprint,
    stage_lock_name,
    write_attempt,
    write_record,
)


class StageFailed(RelightAnyoneError, RuntimeError):
    """A stage's command failed or could not start; the message says which and where its log is."""


class MissingInput(StageFailed):
    """An input of a stage does not exist (and no earlier stage will produce it)."""


@dataclass
class Pipeline:
    """Stages in file order, the stages each one depends on, and a topological order."""

    spec: PipelineSpec
    stages: dict[str, StageSpec]
    dependencies: dict[str, tuple[str, ...]]
    order: list[str]

    def downstream(self, names: Iterable[str]) -> set[str]:
        """``names`` and every stage that depends on them, directly or not."""
        result = set(names)
        for name in self.order:  # topological, so one pass reaches every descendant
            if any(d in result for d in self.dependencies[name]):
                result.add(name)
        return result

    def upstream(self, name: str) -> set[str]:
        """Every stage ``name`` depends on, directly or not."""
        result: set[str] = set()
        todo = list(self.dependencies[name])
        while todo:
            current = todo.pop()
            if current not in result:
                result.add(current)
                todo.extend(self.dependencies[current])
        return result

    def producer_of(self, path: Path) -> str | None:
        """The stage whose output is ``path`` or contains it."""
        for name, stage in self.stages.items():
            if path == stage.output or stage.output in path.parents:
                return name
        return None


def _related(a: Path, b: Path) -> bool:
    """Whether one path is the other or lies inside it."""
    return a == b or a in b.parents or b in a.parents


def build_pipeline(spec: PipelineSpec) -> Pipeline:
    """Infer dependencies from inputs and ``after:``; raises PipelineError for unknown stages, overlapping
    outputs and cycles, naming the file, line and stages."""
    stages = {stage.name: stage for stage in spec.stages}
    names = list(stages)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            if _related(stages[a].output, stages[b].output):
                raise PipelineError(
                    f"{spec.where('stages', b, 'output')}: output {stages[b].output} overlaps the output of "
                    f"stage {a!r} ({stages[a].output}); give every stage its own directory"
                )
    dependencies: dict[str, tuple[str, ...]] = {}
    for name, stage in stages.items():
        found: list[str] = []
        for position, (after, line) in enumerate(zip(stage.after, stage.after_lines, strict=True)):
            if after not in stages:
                raise PipelineError(
                    f"{spec.source}:{line} stages.{name}.after[{position}]: unknown stage {after!r} "
                    f"(stages: {', '.join(names)})"
                )
            found.append(after)
        for path, line in zip(stage.inputs, stage.input_lines, strict=True):
            if _related(path, stage.output):
                raise PipelineError(
                    f"{spec.source}:{line} stages.{name}.inputs: {path} overlaps the stage's own output "
                    f"{stage.output}; a stage cannot read what it writes"
                )
            found.extend(other for other in names if other != name and _related(path, stages[other].output))
        if name in found:
            raise PipelineError(
                f"{spec.where('stages', name, 'after')}: stage {name!r} cannot come after itself"
            )
        dependencies[name] = tuple(dict.fromkeys(found))
    return Pipeline(spec, stages, dependencies, _topological_order(spec, names, dependencies))


def _topological_order(
    spec: PipelineSpec, names: list[str], dependencies: dict[str, tuple[str, ...]]
) -> list[str]:
    """Kahn's algorithm taking the first ready stage in file order; a cycle raises naming its stages and lines."""
    remaining = {name: set(dependencies[name]) for name in names}
    order: list[str] = []
    while remaining:
        ready = [name for name in names if name in remaining and not remaining[name]]
        if not ready:
            cycle = _find_cycle(remaining)
            lines = ", ".join(f"{n} (line {spec.lines.get(('stages', n), '?')})" for n in cycle[:-1])
            raise PipelineError(
                f"{spec.source}: stages depend on each other in a cycle: {' -> '.join(cycle)}; "
                f"check the inputs/after of {lines}"
            )
        # One at a time, the first ready stage in file order: the order reads like the file.
        order.append(ready[0])
        del remaining[ready[0]]
        for waiting in remaining.values():
            waiting.discard(ready[0])
    return order


def _find_cycle(remaining: dict[str, set[str]]) -> list[str]:
    start = next(iter(remaining))
    path = [start]
    while True:
        following = sorted(remaining[path[-1]])[0]
        if following in path:
            return [*path[path.index(following) :], following]
        path.append(following)


def load_pipeline(path: Path | str, overrides: dict[str, str] | None = None) -> Pipeline:
    """Parse and check the pipeline file at ``path`` (see ``pipeline_file`` for the format)."""
    return build_pipeline(parse_pipeline(path, overrides))


def load_hash_cache(pipeline: Pipeline) -> HashCache:
    """A cache filled from every stage's record (its output files and its external input files)."""
    cache = HashCache()
    for stage in pipeline.stages.values():
        record = read_record(stage.output)
        if record is None:
            continue
        cache.add_listing(stage.output, record["outputs"].get("files", {}))
        for path, entry in record.get("inputs", {}).items():
            cache.add_listing(Path(path), entry.get("files", {}))
    return cache


# ---------------------------------------------------------------------------------------- planning


@dataclass
class Decision:
    """Whether a stage runs and why; ``inputs`` holds the fingerprints computed while deciding."""

    stage: str
    run: bool
    reason: str
    inputs: dict[str, Fingerprint] = field(default_factory=dict)
    outputs: Fingerprint | None = None


def _check_selection(pipeline: Pipeline, names: Iterable[str], option: str) -> list[str]:
    names = list(names)
    unknown = [n for n in names if n not in pipeline.stages]
    if unknown:
        raise PipelineError(f"{option} {unknown[0]}: no such stage (stages: {', '.join(pipeline.order)})")
    return names


def decide(
    pipeline: Pipeline, name: str, cache: HashCache, forced: dict[str, str], pending: set[str]
) -> Decision:
    """Decide whether stage ``name`` runs. ``forced`` maps forced stages to the reason; ``pending`` are
    upstream stages that will run first (their outputs cannot be fingerprinted yet)."""
    stage = pipeline.stages[name]
    if name in forced:
        return Decision(name, True, forced[name])
    waiting = [d for d in pipeline.dependencies[name] if d in pending]
    if waiting:
        stages, verb = ("stage", "runs") if len(waiting) == 1 else ("stages", "run")
        return Decision(
            name, True, f"upstream {stages} {', '.join(waiting)} {verb} first (inputs checked again then)"
        )
    inputs = {}
    for path in stage.inputs:
        found = fingerprint_path(path, cache)
        if found is None:
            raise MissingInput(
                f"stage {name!r}: input {path} does not exist; produce it first or fix the path in "
                f"{pipeline.spec.source}"
            )
        inputs[str(path)] = found
    if not stage.output.is_dir():
        return Decision(name, True, "output missing", inputs)
    record = read_record(stage.output)
    if record is None:
        return Decision(name, True, "no complete _stage.json (never run, or interrupted)", inputs)
    if record.get("config") != stage_config(stage):
        return Decision(name, True, "config changed", inputs)
    if record.get("package_version") != package_version():
        return Decision(
            name,
            True,
            f"package version changed ({record.get('package_version')} -> {package_version()})",
            inputs,
        )
    recorded_inputs = record.get("inputs", {})
    for path, fingerprint in inputs.items():
        if path not in recorded_inputs:
            return Decision(name, True, f"input {path} added", inputs)
        if recorded_inputs[path].get("digest") != fingerprint.digest:
            return Decision(name, True, f"input {path} changed", inputs)
    for path in recorded_inputs:
        if path not in inputs:
            return Decision(name, True, f"input {path} removed", inputs)
    current = fingerprint_path(stage.output, cache)
    recorded_outputs = record["outputs"]
    if current is None or current.digest != recorded_outputs.get("digest"):
        difference = compare_listings(recorded_outputs.get("files", {}), current.files if current else {})
        return Decision(name, True, f"output changed ({difference or 'different content'})", inputs)
    digests = {path: f.digest for path, f in inputs.items()}
    if record.get("fingerprint") != stage_fingerprint(stage_config(stage), digests, package_version()):
        return Decision(name, True, "fingerprint changed", inputs)
    return Decision(name, False, "up to date", inputs, current)


def forced_reasons(pipeline: Pipeline, force: Iterable[str]) -> dict[str, str]:
    """Forced stages and everything downstream of them, with the reason."""
    reasons: dict[str, str] = {}
    names = _check_selection(pipeline, force, "--force")
    for name in names:
        reasons[name] = "forced (--force)"
    for name in names:
        for other in sorted(pipeline.downstream([name]) - set(reasons), key=pipeline.order.index):
            reasons[other] = f"downstream of forced stage {name}"
    return reasons


def _selected(pipeline: Pipeline, only: Iterable[str]) -> set[str]:
    only = _check_selection(pipeline, only, "--only")
    if not only:
        return set(pipeline.order)
    for name in only:
        for needed in sorted(pipeline.upstream(name) - set(only)):
            if read_record(pipeline.stages[needed].output) is None:
                raise StageFailed(
                    f"--only {name}: it needs stage {needed!r}, which has not completed; "
                    f"run it first (add --only {needed}) or run the whole pipeline"
                )
    return set(only)


def plan(
    pipeline: Pipeline, force: Iterable[str] = (), only: Iterable[str] = (), cache: HashCache | None = None
) -> list[Decision]:
    """What a run would do, stage by stage in execution order, without running anything."""
    cache = cache or load_hash_cache(pipeline)
    forced = forced_reasons(pipeline, force)
    selected = _selected(pipeline, only)
    pending: set[str] = set()
    decisions = []
    for name in pipeline.order:
        if name not in selected:
            decisions.append(Decision(name, False, "not selected (--only)"))
            continue
        try:
            decision = decide(pipeline, name, cache, forced, pending)
        except MissingInput as error:  # the plan is still worth seeing whole; a run stops here
            decision = Decision(name, True, f"cannot run: {str(error).split(': ', 1)[1]}")
        if decision.run:
            pending.add(name)
        decisions.append(decision)
    return decisions


# --------------------------------------------------------------------------------------- execution


@dataclass
class StageResult:
    """What happened to one stage in a run: ``status`` is "ran", "skipped" or "not selected"."""

    stage: str
    status: str
    reason: str
    elapsed_s: float = 0.0


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _prepare_output(output: Path, fingerprint: str, pipeline_source: Path) -> None:
    """Make ``output`` ready for a run of ``fingerprint``: stale work removed, old record and logs deleted
    first (a partial run must never look complete), the attempt marked."""
    if output.is_dir() and (
        read_record(output) is not None or read_attempt(output) not in (None, fingerprint)
    ):
        _remove_stale_output(output, pipeline_source)
    output.mkdir(parents=True, exist_ok=True)
    write_attempt(output, fingerprint)
    (output / STAGE_RECORD_NAME).unlink(missing_ok=True)
    (output / STAGE_LOG_NAME).unlink(missing_ok=True)
    live_log_path(output).unlink(missing_ok=True)  # left by a runner that was killed
    for leftover in output.glob("_stage.json.*.tmp"):
        leftover.unlink(missing_ok=True)


def _remove_stale_output(output: Path, pipeline_source: Path) -> None:
    """Delete a stage's stale output folder, refusing folders that obviously hold more than one stage's
    results (a filesystem root, the home folder, the working folder or the pipeline file's folder)."""
    resolved = output.resolve()
    protected = [Path(resolved.anchor), Path.home().resolve(), Path.cwd().resolve()]
    if resolved in protected or Path(pipeline_source).resolve().is_relative_to(resolved):
        raise StageFailed(
            f"stage output {output} holds results of another config or inputs, which the stage would resume "
            "from, but it is too broad a folder to clear; give the stage an output folder of its own"
        )
    shutil.rmtree(output)


def run_stage(
    pipeline: Pipeline, decision: Decision, cache: HashCache, echo: BinaryIO | None, announce=None
) -> dict:
    """Run one stage's command and, when it succeeds, write and return its ``_stage.json`` record.

    The stage's output is locked while it runs (:func:`stage_lock_name`): another runner reaching the same
    stage stops with an error naming this one instead of clearing the output under it. Without ``echo``
    the path of the live log is passed to ``announce`` (for ``tail -f``)."""
    output = pipeline.stages[decision.stage].output
    with output_lock(output.parent, stage_lock_name(output)):
        return _run_stage(pipeline, decision, cache, echo, announce)


def _run_stage(
    pipeline: Pipeline, decision: Decision, cache: HashCache, echo: BinaryIO | None, announce
) -> dict:
    stage = pipeline.stages[decision.stage]
    inputs = decision.inputs or {str(p): fingerprint_path(p, cache) for p in stage.inputs}
    missing = [path for path, fingerprint in inputs.items() if fingerprint is None]
    if missing:
        raise StageFailed(
            f"stage {stage.name!r}: input {missing[0]} does not exist (did an upstream stage fail?)"
        )
    digests = {path: fingerprint.digest for path, fingerprint in inputs.items()}
    _prepare_output(
        stage.output, stage_fingerprint(stage_config(stage), digests, package_version()), pipeline.spec.source
    )
    argv = stage_argv(stage.kind, stage.args)
    started, clock = _now(), time.perf_counter()
    log_path = live_log_path(stage.output)
    if echo is None and announce is not None:
        announce(f"    live log: {log_path} (moved to {stage.output / STAGE_LOG_NAME} at the end)")
    try:
        with open(log_path, "wb") as log:
            log.write(f"# stage {stage.name}, started {started}\n# {' '.join(argv)}\n".encode())
            log.flush()
            try:
                status = run_with_log(argv, log, stage.env, echo)
            except FileNotFoundError as error:
                log.write(f"{error}\n".encode())
                status = None
    finally:  # also on Ctrl-C: the log of an interrupted stage is worth reading
        stage.output.mkdir(parents=True, exist_ok=True)  # the command may have removed it
        shutil.move(log_path, stage.output / STAGE_LOG_NAME)
    if status != 0:
        what = "could not start" if status is None else f"failed with exit status {status}"
        raise StageFailed(
            f"stage {stage.name!r} {what}; its output is in {stage.output / STAGE_LOG_NAME}. Fix the cause and "
            f"run the pipeline again (finished stages are skipped)"
        )
    outputs = fingerprint_path(stage.output, cache)
    assert outputs is not None  # the folder was created above
    record = _record(pipeline, stage, inputs, outputs)
    record.update(
        command=argv, started=started, finished=_now(), elapsed_s=round(time.perf_counter() - clock, 3)
    )
    write_record(stage.output, record)
    attempt_path(stage.output).unlink(missing_ok=True)
    return record


def _record(
    pipeline: Pipeline, stage: StageSpec, inputs: dict[str, Fingerprint], outputs: Fingerprint
) -> dict:
    digests = {path: fingerprint.digest for path, fingerprint in inputs.items()}
    return {
        "record_format": RECORD_FORMAT,
        "stage": stage.name,
        "status": "complete",
        "pipeline": str(pipeline.spec.source),
        "description": stage.description,
        "config": stage_config(stage),
        "package_version": package_version(),
        "fingerprint": stage_fingerprint(stage_config(stage), digests, package_version()),
        "inputs": {
            path: {"digest": fingerprint.digest}
            # External inputs keep their file listing here: it is their hash cache for the next run.
            | ({} if pipeline.producer_of(Path(path)) else {"files": listing_to_json(fingerprint.files)})
            for path, fingerprint in inputs.items()
        },
        "outputs": {"digest": outputs.digest, "files": listing_to_json(outputs.files)},
    }


def refresh_record(pipeline: Pipeline, decision: Decision) -> None:
    """Rewrite the record of an up-to-date stage with the current (size, mtime) of its files, so files
    that were touched but not changed are not hashed again on the next run; digests stay the same."""
    stage = pipeline.stages[decision.stage]
    record = read_record(stage.output)
    if record is None or decision.outputs is None:
        return
    record.update(_record(pipeline, stage, decision.inputs, decision.outputs))
    write_record(stage.output, record)


def execute(
    pipeline: Pipeline,
    force: Iterable[str] = (),
    only: Iterable[str] = (),
    echo: BinaryIO | None = None,
    announce=print,
) -> list[StageResult]:
    """Run the pipeline: every selected stage in order, skipping those that are up to date.

    ``echo`` receives the stages' own output (None: only their ``_stage.log``); ``announce`` gets one line
    per stage event. Raises StageFailed at the first stage that fails.
    """
    cache = load_hash_cache(pipeline)
    forced = forced_reasons(pipeline, force)
    selected = _selected(pipeline, only)
    results = []
    total = len(pipeline.order)
    for position, name in enumerate(pipeline.order, start=1):
        prefix = f"[{position}/{total}] {name}"
        if name not in selected:
            results.append(StageResult(name, "not selected", "--only"))
            continue
        hashed_before = cache.hashed_files
        decision = decide(pipeline, name, cache, forced, pending=set())
        if not decision.run:
            if cache.hashed_files != hashed_before:
                refresh_record(pipeline, decision)
            announce(f"{prefix}: skipped ({decision.reason})")
            results.append(StageResult(name, "skipped", decision.reason))
            continue
        announce(f"{prefix}: running ({decision.reason})")
        clock = time.perf_counter()
        try:
            run_stage(pipeline, decision, cache, echo, announce)
        except StageFailed:
            announce(f"{prefix}: FAILED after {time.perf_counter() - clock:.1f} s")
            raise
        elapsed = time.perf_counter() - clock
        announce(f"{prefix}: done in {elapsed:.1f} s")
        results.append(StageResult(name, "ran", decision.reason, elapsed))
    return results
