"""A run's CSV tables read through the gate: no link, bounded, every row checked before any is used.

``metrics.csv``, ``eval.csv``, ``eval_levels.csv`` and ``eval_rollouts.csv`` are appended to one
row at a time by ``march.train`` (:mod:`march.learn.metrics`); a resume drops the rows past its
checkpoint, and the figures read them all. Each is read here once, as the run directory's other
files are (:mod:`march.store.bounded_read`): no symbolic link, a regular file of at most
:data:`MAX_TABLE_BYTES`, UTF-8; then every row is checked - as many fields as the header, a
``stage`` that is a word, an ``iteration`` that is a whole number, every other field empty or a
number - and the first bad row is one :class:`~march.store.bounded_read.FileRefused` line naming
the file, its line and the field. A torn last row (no line break at its end: a kill cut its
write short) is left out and reported, not refused: the resume that reads it drops it.

:func:`check_run_tables` checks every table of a run at once; ``march.train resume=`` calls it
before anything in the directory changes (config.yaml, status.json, the tables themselves).
Standard library only.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from march.store.bounded_read import FileRefused, read_bytes

TABLES = ("metrics.csv", "eval.csv", "eval_levels.csv", "eval_rollouts.csv")
"""The CSV tables ``march.train`` writes into a run directory."""
MAX_TABLE_BYTES = 1 << 30
"""metrics.csv of a 20,000-iteration teacher with per-term columns is ~15 MB; eval_rollouts.csv
of a paper-scale run ~50 MB. A larger file is not one march wrote."""
TEXT_COLUMNS = frozenset({"stage"})
"""Columns holding words; every other column holds numbers (or nothing: a NaN is written empty)."""
_STAGE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}")
_WHOLE = re.compile(r"[0-9]{1,12}")


@dataclass
class Table:
    """A table as read: its header, its rows (field name -> text), and whether its last row was
    torn (left out)."""

    header: list[str]
    rows: list[dict[str, str]] = field(default_factory=list)
    torn: str | None = None

    def number(self, row: dict[str, str], key: str) -> float:
        """The number in ``row[key]`` (NaN when empty or absent); the row is already checked."""
        text = row.get(key, "")
        return float(text) if text else math.nan


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_table(path: Path, label: str | None = None) -> Table | None:
    """The table ``path`` with every row checked (module docstring), or None without the file;
    :class:`FileRefused` in one line naming ``label`` (default: the path), its line and field."""
    path = Path(path)
    label = label or str(path)
    try:
        data = read_bytes(path, label, MAX_TABLE_BYTES, "a table march.train wrote")
    except FileRefused as err:
        if "no such file" in str(err):
            return None
        raise
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        raise FileRefused(f"{label}: not UTF-8 text (byte {err.start}); not read") from None
    if not text:
        return Table(header=[])
    lines = text.splitlines(keepends=True)
    torn = None
    if not lines[-1].endswith(("\n", "\r")):
        torn = lines.pop().strip()
    try:
        parsed = list(csv.reader(lines))
    except csv.Error as err:
        raise FileRefused(f"{label}: not a CSV table ({err})") from None
    if not parsed:
        return Table(header=[], torn=torn)
    header = parsed[0]
    if len(set(header)) != len(header) or not all(header):
        raise FileRefused(f"{label}: its header names a column twice or names an empty one")
    table = Table(header=header, torn=torn)
    for n, fields in enumerate(parsed[1:], start=2):
        if not fields:
            continue
        if len(fields) != len(header):
            if n == len(parsed) and len(fields) < len(header):
                table.torn = ",".join(fields)  # a row cut short by a kill, then a line break
                continue
            raise FileRefused(
                f"{label}: line {n} has {len(fields)} fields, its header {len(header)}; not a "
                "table march wrote (restore the file or start a new run)"
            )
        row = dict(zip(header, fields, strict=True))
        for key, value in row.items():
            if key == "stage":
                ok = bool(_STAGE.fullmatch(value))
                want = "a stage name"
            elif key == "iteration":
                ok = bool(_WHOLE.fullmatch(value))
                want = "a whole number"
            elif key in TEXT_COLUMNS:
                continue
            else:
                ok = value == "" or _is_number(value)
                want = "a number"
            if not ok:
                shown = value if len(value) <= 40 else value[:37] + "..."
                raise FileRefused(
                    f"{label}: line {n}, column {key}: {shown!r} is not {want}; not a table "
                    "march wrote (restore the file or start a new run)"
                )
        table.rows.append(row)
    return table


def check_run_tables(run_dir: Path, option: str = "resume") -> None:
    """Every table of ``run_dir`` read and checked (:func:`read_table`); the first bad row is one
    :class:`FileRefused` line naming ``option=<run_dir>`` and the file."""
    for name in TABLES:
        path = Path(run_dir) / name
        read_table(path, f"{option}={run_dir}: {path}")
