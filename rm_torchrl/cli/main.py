"""rmrl: refine offline RL datasets with event-ordered reward machines, train and evaluate on them, report."""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

# Back large CPU tensors with transparent huge pages: refinement allocates a few big tensors,
# and first-touch page faults would otherwise cost as much as the work itself.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")


def _reopen_closed_streams() -> None:
    """A command started with stdout or stderr closed (``2>&-``) writes them to /dev/null: Python would set the
    stream to None (prints then land elsewhere), and libraries that load theirs through fd 2 (glfw) fail."""
    for fd, name in ((1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
        except OSError:
            null = os.open(os.devnull, os.O_WRONLY)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
            os.set_inheritable(fd, True)  # as a standard stream is: child processes write there too
            setattr(sys, name, open(fd, "w", closefd=False))
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))


_reopen_closed_streams()  # before any import opens a file, which would take a closed descriptor's number

import importlib  # noqa: E402

from rm_torchrl.errors import RMError  # noqa: E402
from rm_torchrl.launch.signals import exit_status  # noqa: E402

#: ``rmrl COMMAND``: the module under rm_torchrl/cli/ holding its ``HELP``, ``add_arguments(parser)`` and ``run(args)``
#: (and optionally ``DESCRIPTION``, and ``ADD_HELP = False`` where it brings its own -h)
COMMANDS = {
    "refine": "refine",
    "inspect": "inspect_events",
    "rm-graph": "graph",
    "train": "train",
    "evaluate": "evaluate",
    "report": "report",
    "import-d4rl": "import_d4rl",
    "generate": "generate",
    "demo": "demo",
}


def command_module(name: str):
    """The adapter module of ``rmrl NAME``; each imports its library code only when it runs."""
    return importlib.import_module(f"rm_torchrl.cli.{COMMANDS[name]}")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("rm_torchrl")
    except PackageNotFoundError:  # run from a checkout that was never installed
        from rm_torchrl import __version__

        return __version__


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``rmrl`` parser; given the command line, only its command's own arguments are built (some build
    theirs from the library: ``rmrl generate`` lists the generators), so a command imports no other's code."""
    wanted = None if argv is None else next((a for a in argv if not a.startswith("-")), "")
    parser = argparse.ArgumentParser(prog="rmrl", description=__doc__)
    parser.add_argument("--version", action="version", version=f"rmrl {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        module = command_module(name)
        p = sub.add_parser(name, help=module.HELP, description=getattr(module, "DESCRIPTION", None),
                           add_help=getattr(module, "ADD_HELP", True))
        if wanted is None or name == wanted:
            module.add_arguments(p)
        p.set_defaults(run=module.run)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that every command's clean-up runs (temporary outputs are removed)."""

    signum = signal.SIGTERM
    message = "terminated (SIGTERM); nothing was written"


def _terminate(signum, frame):
    raise Terminated


def main(argv: list[str] | None = None) -> int:
    from rm_torchrl.env_vars import check_minari_path, check_mujoco_gl

    try:  # before the parser imports the commands' modules, some of which import MuJoCo
        check_mujoco_gl()
        check_minari_path()
    except RMError as err:
        print(f"rmrl: error: {err}", file=sys.stderr)
        return 2
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser(argv).parse_args(argv)  # --help and --version exit here, having imported no torch
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)  # the trainer checkpoints on it instead, inside its loop
    try:
        return args.run(args) or 0
    except RMError as err:
        print(f"rmrl {args.command}: error: {err}", file=sys.stderr)
        return err.exit_status
    except BrokenPipeError:  # `rmrl rm-graph ... | head`: the reader has what it wanted
        _quiet_stdout()
        return 0
    except OSError as err:  # a write the command did not foresee: a full disk or stdout, a name too long
        where = f": {err.filename}" if err.filename else " (writing the output)"
        _quiet_stdout()  # what stdout still buffers would fail again at exit
        print(f"rmrl {args.command}: error: {err.strerror or err}{where}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        return exit_status(err, f"rmrl {args.command}")


def _quiet_stdout() -> None:
    """Points stdout at /dev/null, so that flushing it at exit cannot fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


if __name__ == "__main__":
    sys.exit(main())
