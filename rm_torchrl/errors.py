"""One exception type for every problem a user can fix, so the CLI can print it without a traceback."""


class RMError(ValueError):
    """Bad input to rm_torchrl: a malformed spec, wrong shapes, NaNs, empty data, bad options."""


def yaml_problem(err) -> str:
    """A one-line description of a PyYAML error: what is wrong and where."""
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    mark = getattr(err, "problem_mark", None)
    return f"{problem} (line {mark.line + 1}, column {mark.column + 1})" if mark else problem
