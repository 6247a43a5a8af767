"""The README's quick start, verbatim, in a fresh copy of the checkout: a new venv, ``pip install .`` and
``rmrl demo`` run from the clone (the demo's budget made tiny), which must write its report."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: appended to the quick start's `rmrl demo`: the same demo at a test's budget
TINY = "--steps 10 --seeds 1 --episodes 1 trainer.compile=false eval.max_steps=5"


def quick_start() -> str:
    """The first ```bash block under the README's "## Quick start"."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1]
    return re.search(r"```bash\n(.*?)\n```", section, re.S).group(1).strip()


def fresh_clone(dest: Path) -> Path:
    """The checkout's files as a clone has them (tracked and not ignored), uncommitted changes included."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, capture_output=True,
                            check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        if (ROOT / name).is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, dest / name)
    return dest


def test_the_quick_start_is_one_line_ending_in_the_demo():
    line = quick_start()
    assert "\n" not in line and line.endswith("rmrl demo --out runs/demo"), line


@pytest.mark.slow
def test_the_quick_start_runs_verbatim_in_a_fresh_clone(tmp_path):
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    clone = fresh_clone(tmp_path / "clone")
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                  if not p.startswith(str(Path(sys.prefix))))
    env.update(MUJOCO_GL="egl", OMP_NUM_THREADS="1", MINARI_DATASETS_PATH=str(tmp_path / "minari"))
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", f"{quick_start()} {TINY}"], cwd=clone, env=env,
                          capture_output=True, text=True, timeout=1200)
    if done.returncode != 0 and "No matching distribution" in done.stderr:
        pytest.skip("no package index to install the project's dependencies from")
    assert done.returncode == 0, done.stderr[-3000:]
    report = clone / "runs" / "demo" / "report"
    assert (report / "demo.md").is_file() and (report / "results.md").is_file()
    installed = subprocess.run([str(clone / ".venv" / "bin" / "python"), "-c",
                                "import rm_torchrl; print(rm_torchrl.__file__)"], cwd=tmp_path, capture_output=True,
                               text=True, check=True).stdout
    assert ".venv" in installed  # the launcher ran the installed copy, and so did every run it started
