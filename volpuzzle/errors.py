"""The error types. Every expected failure is a VolpuzzleError; the CLI prints its message as one line."""


class VolpuzzleError(Exception):
    """Base of every error a user can cause: bad spec, bad model, unbuildable puzzle, failed export."""


class SpecError(VolpuzzleError):
    """The spec file is wrong. `problems` lists every mistake as 'key.path: what is wrong (got X, expected Y)'."""

    def __init__(self, problems, source=None):
        if isinstance(problems, str):
            problems = [problems]
        self.problems = list(problems)
        self.source = source
        head = f"{source}: " if source else ""
        if len(self.problems) == 1:
            msg = head + self.problems[0]
        else:
            msg = head + f"{len(self.problems)} problems: " + "; ".join(self.problems)
        super().__init__(msg)


class ModelError(VolpuzzleError):
    """A model file or model object is unreadable, unsupported, or geometrically invalid."""


class GeometryError(VolpuzzleError):
    """The geometry engine failed or a built piece breaks an invariant."""


class ExportError(VolpuzzleError):
    """Output could not be written."""


def one_line(message) -> str:
    """A message (or an exception) on one line: a path or a value with a newline in it must not break the one-line
    rule of the command line's errors."""
    return " ".join(str(message).split("\n")).replace("\r", " ")
