"""Errors the command line reports as one line and exit code 2 (bad input, missing system pieces)."""


class BenchError(Exception):
    """A problem the user can fix: the message is one line saying what was wrong and what is allowed."""

    exit_code = 2


class SpecError(BenchError):
    """A spec file, preset or override that cannot be used."""


class DataError(BenchError):
    """A dataset that is missing, empty, corrupt or does not fit the request."""


class SystemRequirementError(BenchError):
    """A system library (for example GL for headless rendering) is missing."""


class TrainingError(BenchError):
    """Training stopped without a usable model (for example a NaN loss)."""


class BenchWarning(UserWarning):
    """Something the user should know, shown by the command line as one line on stderr."""


def did_you_mean(kind: str, name: str, valid: list[str]) -> str:
    """One line naming an unknown `name`, the closest valid names and all valid names."""
    import difflib

    close = difflib.get_close_matches(name, valid, n=3, cutoff=0.5)
    hint = f" did you mean {', '.join(close)}?" if close else ""
    return f"unknown {kind} {name!r};{hint} valid: {', '.join(sorted(valid))}"
