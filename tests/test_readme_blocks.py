"""Every Python block of the README runs, from an empty directory, after the commands its `# needs:` lines name."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
#: appended to a needed `rmrl train`: the same run at a test's budget
SHORT_TRAIN = ["trainer.steps=10", "trainer.compile=false", "trainer.threads=1", "eval.every=10", "eval.episodes=1",
               "eval.max_steps=5", "--no-progress"]


def python_blocks() -> list[tuple[int, str]]:
    """(line, code) of each ```python block."""
    lines, blocks, start = README.read_text().splitlines(), [], None
    for i, line in enumerate(lines, 1):
        if line.strip() == "```python":
            start = i
        elif line.strip() == "```" and start is not None:
            blocks.append((start, "\n".join(lines[start:i - 1])))
            start = None
    return blocks


def needs(code: str) -> list[list[str]]:
    """The commands a block's ``# needs:`` lines name (what it follows in the README's prose)."""
    found = [shlex.split(m.split("(")[0]) for m in re.findall(r"^# needs: (.+)$", code, re.M)]
    return [[sys.executable, "-m", "rm_torchrl.cli.main", *cmd[1:], *(SHORT_TRAIN if cmd[1] == "train" else [])]
            if cmd[0] == "rmrl" else cmd for cmd in found]


BLOCKS = python_blocks()


def test_the_readme_has_python_blocks():
    assert len(BLOCKS) >= 4


@pytest.mark.parametrize("line,code", BLOCKS, ids=[f"line{n}" for n, _ in BLOCKS])
@pytest.mark.slow
def test_readme_python_block_runs(tmp_path, line, code):
    env = {**os.environ, "MINARI_DATASETS_PATH": str(tmp_path / "minari"), "MUJOCO_GL": "egl",
           "OMP_NUM_THREADS": "1"}
    for cmd in needs(code):
        done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"README line {line} needs {cmd}: {done.stderr[-2000:]}"
    ran = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=600)
    assert ran.returncode == 0, f"README block at line {line}: {ran.stderr[-3000:]}"
