"""Reading a pipeline file: YAML with line numbers, ``${variables}`` and the stage declarations.

A pipeline file has two sections::

    vars:                      # defaults, overridden by `relightanyone run ... --var out=/scratch/demo`
      out: demo-out
    stages:
      world:                   # stage name: letters, digits, '-', '_', '.'
        run: [synth, --preset, tiny, --out, "${output}", --overwrite]   # a relightanyone sub-command
        output: ${out}/world   # the one output directory; `_stage.json` and `_stage.log` land here
      checksum:
        command: [sha256sum, "${out}/world/world.json"]                # any executable
        inputs: ["${out}/world"]                                       # files or folders it reads
        output: ${out}/checksum
        after: [world]         # explicit ordering, rarely needed (inputs already imply it)
        env: {OMP_NUM_THREADS: "1"}

Strings may use ``${name}`` for a variable of ``vars:`` (which may use each other), ``${output}`` (this
stage's output directory), ``${stage}`` (its name), ``${python}`` (the running interpreter) and
``${pipeline_dir}`` (the folder of the YAML file); ``$$`` is a literal ``$``. ``run`` and ``command`` take a
list of arguments or one string split like a shell would (``shlex``). Every error names the file, the line
and the key.
"""

from __future__ import annotations

import os
import re
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from relightanyone.errors import InputError
from relightanyone.format.schema import check_name

STAGE_NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
VARIABLE_PATTERN = re.compile(r"\$(\$|\{([A-Za-z_][A-Za-z0-9_.-]*)\})")
STAGE_KEYS = ("run", "command", "output", "inputs", "after", "env", "description")
BUILTIN_STAGE_VARIABLES = ("output", "stage")


class PipelineError(InputError):
    """A pipeline file is malformed; the message names the file, line and key."""


@dataclass(frozen=True)
class StageSpec:
    """One stage as declared, variables already substituted.

    ``kind`` is ``"run"`` (``args`` follow ``relightanyone``) or ``"command"`` (``args[0]`` is the
    executable). Paths are absolute (relative ones are taken from the working directory of ``run``).
    """

    name: str
    kind: str
    args: tuple[str, ...]
    output: Path
    inputs: tuple[Path, ...]
    after: tuple[str, ...]
    env: dict[str, str]
    description: str
    line: int
    input_lines: tuple[int, ...]
    after_lines: tuple[int, ...]


@dataclass
class PipelineSpec:
    """A parsed pipeline file: its stages in file order and the variables used."""

    source: Path
    stages: list[StageSpec]
    variables: dict[str, str]
    lines: dict[tuple[Any, ...], int] = field(default_factory=dict)

    def where(self, *key: Any) -> str:
        """``"file.yaml:12 stages.world.output"`` for error messages."""
        line = self.lines.get(tuple(key))
        dotted = ".".join(str(k) for k in key)
        return f"{self.source}:{line} {dotted}" if line else f"{self.source} {dotted}"


def _compose_with_lines(text: str, source: Path) -> tuple[Any, dict[tuple[Any, ...], int]]:
    """Parse YAML into plain values plus ``{key path: 1-based line}`` of every mapping key and list item."""
    loader = yaml.SafeLoader(text)
    try:
        root = loader.get_single_node()
    except yaml.YAMLError as error:
        loader.dispose()
        raise PipelineError(f"{source}: not valid YAML ({error})") from None
    lines: dict[tuple[Any, ...], int] = {}

    def build(node: yaml.Node, where: tuple[Any, ...]) -> Any:
        if isinstance(node, yaml.MappingNode):
            out: dict[Any, Any] = {}
            for key_node, value_node in node.value:
                key = build(key_node, where)
                if key in out:
                    raise PipelineError(
                        f"{source}:{key_node.start_mark.line + 1} key {key!r} appears twice in the same mapping"
                    )
                lines[(*where, key)] = key_node.start_mark.line + 1
                out[key] = build(value_node, (*where, key))
            return out
        if isinstance(node, yaml.SequenceNode):
            items = []
            for i, item_node in enumerate(node.value):
                lines[(*where, i)] = item_node.start_mark.line + 1
                items.append(build(item_node, (*where, i)))
            return items
        return loader.construct_object(node, deep=True)

    try:
        return (build(root, ()) if root is not None else None), lines
    finally:
        loader.dispose()


def substitute(text: str, variables: dict[str, str], where: str) -> str:
    """Replace ``${name}`` by ``variables[name]`` and ``$$`` by ``$``; unknown names raise with ``where``."""

    def replace(match: re.Match[str]) -> str:
        if match.group(1) == "$":
            return "$"
        name = match.group(2)
        if name not in variables:
            known = ", ".join(sorted(variables)) or "none"
            raise PipelineError(
                f"{where}: unknown variable ${{{name}}} (known: {known}); define it under vars:"
            )
        return variables[name]

    return VARIABLE_PATTERN.sub(replace, text)


def resolve_variables(
    declared: dict[str, Any], overrides: dict[str, str], builtins: dict[str, str], spec_where
) -> dict[str, str]:
    """Variables of ``vars:`` over ``builtins``, with ``overrides`` applied; values may use each other."""
    raw = {**builtins, **{str(k): str(v) for k, v in declared.items()}, **overrides}
    resolved: dict[str, str] = {}
    visiting: list[str] = []

    def value_of(name: str) -> str:
        if name in resolved:
            return resolved[name]
        if name in visiting:
            loop = " -> ".join([*visiting[visiting.index(name) :], name])
            raise PipelineError(
                f"{spec_where('vars', name)}: variables refer to each other in a loop: {loop}"
            )
        visiting.append(name)

        def replace(match: re.Match[str]) -> str:
            if match.group(1) == "$":
                return "$"
            reference = match.group(2)
            if reference not in raw:
                raise PipelineError(
                    f"{spec_where('vars', name)}: unknown variable ${{{reference}}} in the value of {name}"
                )
            return value_of(reference)

        resolved[name] = VARIABLE_PATTERN.sub(replace, raw[name])
        visiting.pop()
        return resolved[name]

    for name in raw:
        value_of(name)
    return resolved


def _string_list(value: Any, where: str, split: bool) -> list[str]:
    if isinstance(value, str) and split:
        try:
            return shlex.split(value)
        except ValueError as error:
            raise PipelineError(f"{where}: cannot split the command line ({error})") from None
    if isinstance(value, str):
        return [value]
    if not isinstance(value, list) or not all(isinstance(v, (str, int, float)) for v in value):
        raise PipelineError(f"{where}: expected a list of strings, got {value!r}")
    return [str(v) for v in value]


def _absolute(path: str) -> Path:
    """Absolute and normalized (``a/../b`` -> ``b``) so that paths compare by their text; links are kept."""
    return Path(os.path.abspath(os.path.expanduser(path)))


def parse_pipeline(path: Path | str, overrides: dict[str, str] | None = None) -> PipelineSpec:
    """Read the pipeline file at ``path``; ``overrides`` replace values of its ``vars:`` section."""
    source = Path(path)
    try:
        text = source.read_text(encoding="utf-8")
    except OSError as error:
        raise PipelineError(f"{source}: cannot read the pipeline file ({error.strerror})") from None
    document, lines = _compose_with_lines(text, source)
    spec = PipelineSpec(source=source, stages=[], variables={}, lines=lines)
    if not isinstance(document, dict):
        raise PipelineError(f"{source}: expected a mapping with 'vars:' and 'stages:' at the top")
    unknown = sorted(set(document) - {"vars", "stages"})
    if unknown:
        raise PipelineError(f"{spec.where(unknown[0])}: unknown top-level key (expected vars, stages)")
    declared = document.get("vars") or {}
    if not isinstance(declared, dict):
        raise PipelineError(f"{spec.where('vars')}: expected a mapping of name: value")
    overrides = dict(overrides or {})
    for name in overrides:
        if name in BUILTIN_STAGE_VARIABLES:
            raise PipelineError(f"--var {name}: '{name}' is set per stage and cannot be overridden")
    builtins = {"python": sys.executable, "pipeline_dir": str(source.resolve().parent)}
    undeclared = sorted(set(overrides) - set(map(str, declared)) - set(builtins))
    if undeclared:
        raise PipelineError(
            f"--var {undeclared[0]}: {source} has no such variable "
            f"(vars: {', '.join(map(str, declared)) or 'none'})"
        )
    spec.variables = resolve_variables(declared, overrides, builtins, spec.where)
    stages = document.get("stages")
    if not isinstance(stages, dict) or not stages:
        raise PipelineError(f"{spec.where('stages')}: expected a non-empty mapping of stage name: stage")
    for name, body in stages.items():
        spec.stages.append(_parse_stage(spec, str(name), body))
    return spec


def _parse_stage(spec: PipelineSpec, name: str, body: Any) -> StageSpec:
    where = spec.where
    if not STAGE_NAME_PATTERN.match(name):
        raise PipelineError(f"{where('stages', name)}: stage names use letters, digits, '-', '_' and '.'")
    check_name(name, "stage", where("stages", name))
    if not isinstance(body, dict):
        raise PipelineError(f"{where('stages', name)}: expected a mapping with run/command, output, inputs")
    unknown = sorted(set(body) - set(STAGE_KEYS))
    if unknown:
        raise PipelineError(
            f"{where('stages', name, unknown[0])}: unknown key (expected {', '.join(STAGE_KEYS)})"
        )
    kinds = [k for k in ("run", "command") if k in body]
    if len(kinds) != 1:
        raise PipelineError(
            f"{where('stages', name)}: give exactly one of run: (a relightanyone sub-command) "
            "or command: (any executable)"
        )
    kind = kinds[0]
    if "output" not in body or not isinstance(body["output"], str) or not body["output"].strip():
        raise PipelineError(f"{where('stages', name)}: every stage needs output: (its output directory)")
    base = {**spec.variables, "stage": name}
    output = _absolute(substitute(body["output"], base, where("stages", name, "output")))
    variables = {**base, "output": str(output)}

    def strings(key: str, split: bool) -> list[str]:
        if key not in body or body[key] is None:
            return []
        values = _string_list(body[key], where("stages", name, key), split)
        return [substitute(v, variables, where("stages", name, key)) for v in values]

    args = strings(kind, split=True)
    if not args:
        raise PipelineError(f"{where('stages', name, kind)}: the command is empty")
    inputs = tuple(_absolute(p) for p in strings("inputs", split=False))
    after = tuple(strings("after", split=False))
    env_value = body.get("env") or {}
    if not isinstance(env_value, dict):
        raise PipelineError(f"{where('stages', name, 'env')}: expected a mapping of NAME: value")
    env = {
        str(k): substitute(str(v), variables, where("stages", name, "env", k)) for k, v in env_value.items()
    }
    count = {"inputs": len(inputs), "after": len(after)}

    def line_of(key: str, index: int) -> int:  # the item's line; the key's when given as one string
        return spec.lines.get(("stages", name, key, index)) or spec.lines.get(("stages", name, key), 0)

    return StageSpec(
        name=name,
        kind=kind,
        args=tuple(args),
        output=output,
        inputs=inputs,
        after=after,
        env=env,
        description=str(body.get("description") or ""),
        line=spec.lines.get(("stages", name), 0),
        input_lines=tuple(line_of("inputs", i) for i in range(count["inputs"])),
        after_lines=tuple(line_of("after", i) for i in range(count["after"])),
    )


def parse_var_overrides(values: tuple[str, ...] | list[str]) -> dict[str, str]:
    """``["out=/x", "preset=tiny"]`` -> ``{"out": "/x", "preset": "tiny"}``; malformed items raise."""
    out = {}
    for item in values:
        name, sep, value = item.partition("=")
        if not sep or not re.match(r"^[A-Za-z_][A-Za-z0-9_.-]*$", name):
            raise PipelineError(f"--var {item!r}: expected NAME=VALUE")
        out[name] = value
    return out
