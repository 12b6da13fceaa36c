"""Error types shared by every stage.

``InputError`` is raised for bad external input (images, archives, JSON, HTTP
bodies). Its message is one line that names the file or field and the problem,
so the CLI can print it as is and the job service can store it as a failed
stage's reason. Bad input is never retried.
"""

from __future__ import annotations

from pathlib import Path


class GraylightError(Exception):
    """Base of every error Graylight raises on purpose."""


class InputError(GraylightError):
    """Bad external input: ``where`` names the file or field, ``problem`` says what is wrong."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")

    def __reduce__(self) -> tuple[type[InputError], tuple[str, str]]:
        # Process pools pickle exceptions raised in workers; the default would call __init__ with one argument.
        return (type(self), (self.where, self.problem))


def relative_message(exc: InputError, root: str | Path) -> str:
    """``exc``'s one line with its ``where`` made relative to ``root`` when it lies inside it, so
    that a message nested into another (``views[2] (v2): bad capture: ...``) names the file as
    the client wrote it, not where this machine unpacked it."""
    where = Path(exc.where)
    base = Path(root)
    if where.is_absolute() and where.is_relative_to(base):
        return f"{where.relative_to(base).as_posix()}: {exc.problem}"
    return str(exc)
