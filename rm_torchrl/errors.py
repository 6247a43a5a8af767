"""One exception type for every problem a user can fix, so the CLI can print it without a traceback."""
import sys


class RMError(ValueError):
    """Bad input to rm_torchrl: a malformed spec, wrong shapes, NaNs, empty data, bad options."""

    #: what ``rmrl`` exits with on it
    exit_status = 2


def read_yaml(path, what: str):
    """The parsed YAML file at ``path``; ``what`` names it in the error ("recipe", "event spec").

    Every YAML file a user names is read here, so that each command refuses the same way a file that
    cannot be read, is not UTF-8 text, is not YAML, or nests deeper than Python's stack can parse.
    """
    import yaml

    try:
        raw = open(path, "rb").read()
    except OSError as err:
        raise RMError(f"cannot read {what} {path}: {err.strerror}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise RMError(f"{what} {path} is not UTF-8 text: byte {raw[err.start]:#04x} at offset {err.start} "
                      f"({err.reason})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise RMError(f"{what} {path} is not valid YAML: {yaml_problem(err)}") from None
    except RecursionError:
        raise too_deep(what, path) from None


def too_deep(what: str, path) -> RMError:
    """The error for a file whose nesting exhausted Python's stack while a parser (PyYAML, OmegaConf) read it."""
    return RMError(f"{what} {path} nests lists or mappings too deeply to read (beyond Python's recursion limit, "
                   f"{sys.getrecursionlimit()})")


def read_json(path, what: str = ""):
    """The parsed JSON file at ``path``, or a one-line RMError naming it (``what``: "choices file")."""
    import json

    named = f"{what} {path}" if what else str(path)
    try:
        return json.loads(open(path, "rb").read())
    except OSError as err:
        raise RMError(f"cannot read {named}: {err.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise RMError(f"{named} is not valid JSON: {err}") from None


def yaml_problem(err) -> str:
    """A one-line description of a PyYAML error: what is wrong and where."""
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    mark = getattr(err, "problem_mark", None)
    return f"{problem} (line {mark.line + 1}, column {mark.column + 1})" if mark else problem
