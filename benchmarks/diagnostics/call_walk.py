"""The walk a reader takes from ``rmrl train`` to the first gradient update: which of the package's files the
calls enter, in order, and how often the walk climbs back up the layers or returns to a file it had left.

    python benchmarks/diagnostics/call_walk.py [--json] [--show]

It runs ``rmrl train`` in this process on a tiny generated door-like dataset (no evaluation, no compile) under
``sys.setprofile`` and stops at the first call of the update (``gradient_step``). Only calls count (not the
returns to a caller, nor code run at import). A file's *layer* comes from the package's own imports: a folder
(or a top-level module) that imports nothing of the package is layer 0, else one above the highest it imports.

- ``files``: the package files the calls enter;
- ``entries``: the walk's steps (consecutive calls in one file are one step);
- ``climbs``: steps into a file of a higher layer than the one the call came from (a lower layer calling up);
- ``returns``: steps into a file the walk had already entered before and left.
"""
from __future__ import annotations

import argparse
import ast
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "rm_torchrl"


class _Reached(Exception):
    """The walk arrived at the update."""


def unit(path: Path) -> str:
    """The layer unit of a package file: its top folder, or the module itself at the package's top."""
    rel = path.relative_to(PACKAGE)
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def layers() -> dict[str, int]:
    """unit -> layer, from every import of the package in its files (module level or inside functions)."""
    deps: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        here = unit(path)
        deps.setdefault(here, set())
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
            for name in names:
                parts = name.split(".")
                if parts[0] == "rm_torchrl" and len(parts) > 1 and parts[1] != here:
                    deps[here].add(parts[1])
    level: dict[str, int] = {}

    def depth(u: str, seen: tuple = ()) -> int:
        if u in level:
            return level[u]
        if u in seen:  # an import circle: its members share a layer
            return 0
        level[u] = 1 + max((depth(d, (*seen, u)) for d in deps.get(u, ()) if d in deps), default=-1)
        return level[u]

    for u in deps:
        depth(u)
    return level


def walk(tmp: Path) -> list[str]:
    """The package files the calls enter, from ``rmrl train`` to the first update."""
    from rm_torchrl.cli.main import main
    from rm_torchrl.data.synthetic import write_door_like_hdf5

    data = write_door_like_hdf5(tmp / "door-like.hdf5", transitions=2_000)
    entered: list[str] = []

    def profile(frame, event, arg):
        if event != "call" or frame.f_code.co_name == "<module>":
            return
        file = Path(frame.f_code.co_filename).resolve()
        if file.is_relative_to(PACKAGE):
            rel = file.relative_to(ROOT).as_posix()
            if not entered or entered[-1] != rel:
                entered.append(rel)
            if frame.f_code.co_name == "gradient_step":
                raise _Reached

    sys.setprofile(profile)
    try:
        main(["train", f"data.source={data}", "data.events=door", "data.episode_ends=timeouts", "eval.env=",
              "trainer.compile=false", "trainer.steps=2", f"out={tmp}", "name=walk", "--no-progress"])
    except _Reached:
        pass
    finally:
        sys.setprofile(None)
    return entered


def measure(entered: list[str], level: dict[str, int]) -> dict:
    layer_of = {f: level[unit(ROOT / f)] for f in entered}
    climbs = sum(layer_of[b] > layer_of[a] for a, b in zip(entered, entered[1:]))
    returns = sum(f in entered[:i] for i, f in enumerate(entered))
    return {"files": len(set(entered)), "entries": len(entered), "climbs": climbs, "returns": returns,
            "walk": [f"{f} (layer {layer_of[f]})" for f in entered]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--show", action="store_true", help="print the walk, one file a line")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        result = measure(walk(Path(tmp)), layers())
    if not args.show:
        result.pop("walk")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
