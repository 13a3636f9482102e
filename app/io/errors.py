"""One exception type for every bad-input case.

Every problem with user input (a survey directory, an uploaded file, a parameter)
is raised as :class:`InputError`, which names the file, the row and the column so
that an analyst can open the file and find the cell.  ``row`` is the 1-based line
number in the file as a text editor shows it (the header is line 1, the first
data row is line 2); ``None`` when the problem is not tied to one row.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input, located as precisely as possible.

    Parameters
    ----------
    file : str or None
        Path (or upload name) of the offending file.
    row : int or None
        1-based line number in the file (header = 1), or None.
    column : str or None
        Column name, or None.
    message : str
        What is wrong, in words an analyst understands.
    """

    def __init__(self, file: str | None, row: int | None, column: str | None, message: str):
        self.file = None if file is None else str(file)
        self.row = None if row is None else int(row)
        self.column = column
        self.message = message
        super().__init__(self.__str__())

    def __str__(self) -> str:  # "file gnss.csv, row 17, column 'vu': not a number: 'abc'"
        parts = []
        if self.file is not None:
            parts.append(f"file {self.file}")
        if self.row is not None:
            parts.append(f"row {self.row}")
        if self.column is not None:
            parts.append(f"column '{self.column}'")
        where = ", ".join(parts)
        return f"{where}: {self.message}" if where else self.message

    def to_dict(self) -> dict:
        """JSON-able detail for HTTP 4xx responses."""
        return {"file": self.file, "row": self.row, "column": self.column, "message": self.message,
                "detail": str(self)}
