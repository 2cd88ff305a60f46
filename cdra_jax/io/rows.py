"""Where a value of a measurement file sits: the error type that names file, line and column,
and the row context that state sources use to raise it (:mod:`.measurements`,
:mod:`.state_sources`)."""

from __future__ import annotations

from dataclasses import dataclass


class MeasurementFileError(ValueError):
    """A measurement file is malformed; the message names the file, the line and the column.

    Attributes:
        source: the file name (or ``"<measurements>"`` for text).
        line: 1-based line number in the file, or ``None``.
        column: the column name, or ``None``.
    """

    def __init__(
        self,
        source: str,
        what: str,
        *,
        line: int | None = None,
        column: str | None = None,
        header: bool = False,
    ):
        self.source, self.line, self.column, self.what = source, line, column, what
        where = [source]
        if line is not None:
            where.append(f"line {line} (header row)" if header else f"line {line}")
        if column is not None:
            where.append(f"column {column!r}")
        super().__init__(f"{', '.join(where)}: {what}")


@dataclass(frozen=True)
class RowContext:
    """Where the rows handed to a state source came from, to build precise errors.

    Attributes:
        source: file name.
        header_line: 1-based line of the header row.
        lines: 1-based line of each data row.
    """

    source: str
    header_line: int
    lines: tuple[int, ...]

    def error(self, what: str, *, column: str | None = None, row: int | None = None):
        """A :class:`MeasurementFileError` at data row ``row`` (0-based), or the header."""
        line = self.header_line if row is None else self.lines[row]
        return MeasurementFileError(self.source, what, line=line, column=column, header=row is None)
