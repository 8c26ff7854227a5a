"""JSON metrics (a stage's ``metrics.json``, ``evaluation.json``) as HTML tables of rounded scalars.

A nested object whose members are all flat objects sharing keys (``{"held_out": {"d1": {"psnr": ..,
"ssim": ..}, "d2": {..}}}``) becomes a matrix table (rows = members, columns = their keys); everything
else is flattened to dotted keys (``held_out.d1.psnr``) in one key/value table. Short lists of scalars
are shown inline; long numeric lists as their count and range.
"""

from __future__ import annotations

from typing import Any

from relightanyone.pipelines.report.html import esc, format_number, table

INLINE_LIST_LIMIT = 8
TEXT_LIMIT = 200


def _is_scalar(value: Any) -> bool:
    return value is None or isinstance(value, (str, int, float, bool))


def _is_matrix(value: Any) -> bool:
    """An object of >= 2 flat objects (scalar members only) that share at least one key."""
    if not isinstance(value, dict) or len(value) < 2:
        return False
    members = list(value.values())
    if not all(isinstance(m, dict) and m and all(_is_scalar(v) for v in m.values()) for m in members):
        return False
    return bool(set.intersection(*(set(m) for m in members)))


def _display(value: Any) -> object:
    """A scalar or list as a table cell: numbers stay numbers (rounded by the table), the rest text."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value
    if isinstance(value, list):
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value) and value:
            if len(value) <= INLINE_LIST_LIMIT:
                return "[" + ", ".join(format_number(v) for v in value) + "]"
            return f"{len(value)} values, {format_number(min(value))} to {format_number(max(value))}"
        if len(value) <= INLINE_LIST_LIMIT and all(_is_scalar(v) for v in value):
            return "[" + ", ".join(str(v) for v in value) + "]"
        return f"list of {len(value)} items"
    text = "null" if value is None else str(value)
    return text if len(text) <= TEXT_LIMIT else text[: TEXT_LIMIT - 1] + "…"


def split_metrics(values: Any, prefix: str = "") -> tuple[list[tuple[str, Any]], list[tuple[str, dict]]]:
    """(flat ``(dotted key, value)`` pairs, ``(dotted key, matrix object)`` pairs) of a JSON value.

    Lists of objects are descended with their index as a key part; lists of scalars are kept as values.
    """
    flat: list[tuple[str, Any]] = []
    matrices: list[tuple[str, dict]] = []
    if _is_matrix(values):
        return flat, [(prefix, values)]
    if isinstance(values, dict):
        items = list(values.items())
    elif isinstance(values, list) and values and all(isinstance(v, (dict, list)) for v in values):
        items = [(str(i), v) for i, v in enumerate(values)]
    else:
        return [(prefix or "value", values)], matrices
    for key, value in items:
        dotted = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, (dict, list)) and not (isinstance(value, list) and _flat_list(value)):
            if isinstance(value, dict) and not value:
                flat.append((dotted, "{}"))
                continue
            sub_flat, sub_matrices = split_metrics(value, dotted)
            flat.extend(sub_flat)
            matrices.extend(sub_matrices)
        else:
            flat.append((dotted, value))
    return flat, matrices


def _flat_list(value: list) -> bool:
    return not value or not all(isinstance(v, (dict, list)) for v in value)


def metrics_tables(values: Any) -> str:
    """HTML: one matrix table per matrix-shaped object, then one key/value table of the other scalars."""
    flat, matrices = split_metrics(values)
    parts = []
    for name, matrix in matrices:
        columns: list[str] = []
        for member in matrix.values():
            columns.extend(k for k in member if k not in columns)
        rows = [
            [str(row_name), *(_display(member.get(c, "")) for c in columns)]
            for row_name, member in matrix.items()
        ]
        parts.append(f'<p class="muted"><code>{esc(name or "values")}</code></p>\n')
        parts.append(table(["", *columns], rows))
    if flat:
        parts.append(table(["key", "value"], [[key, _display(value)] for key, value in flat]))
    if not parts:
        parts.append(table(["key", "value"], []))
    return "".join(parts)
