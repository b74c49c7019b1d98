"""The README's examples run as written, so the README cannot drift from the code.

Its fenced ``python`` blocks run in order in one interpreter, sharing a namespace as a reader's
session would, and each ``bash`` / ``sh`` / ``shell`` block runs under ``bash -euo pipefail``: all
against a real service (`ServerProcess`: ``canonical serve`` on a free port with a fresh data
directory) that they find through ``CANONICAL_URL``, as the README says, on the real captures in
../shared/data. They run in a scratch folder laid out like a checkout (``.venv`` is the virtualenv
running the tests, ``../shared`` the shared data), so the files they write go there.

The rule for a block that is not run: the line above it (blank lines aside) is
``<!-- not run: REASON -->``, and the reason may not be empty (the set-up commands, which CI runs
itself; a service that runs until stopped). Every other block of a language the README uses must run.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import pytest

from tests.conftest import DATA
from tests.server.harness import REPO, ServerProcess

README = REPO / "README.md"
MAX_LINES = 170
SETUP_COMMANDS = ["make demo", "make test"]
PYTHON, SHELL = "python", ("bash", "sh", "shell")
DRAWN = ("mermaid",)  # pictures, not commands
NOT_RUN = re.compile(r"<!--\s*not run:(.*?)-->")


class Block(NamedTuple):
    """One fenced block of a markdown file."""

    language: str
    line: int  # 1-based line of its first code line, for messages
    code: str
    not_run: str | None  # the reason of a `<!-- not run: REASON -->` on the line above, else None


def fenced_blocks(text: str) -> list[Block]:
    """The fenced (```) blocks of markdown ``text`` in order, with the not-run marker above each."""
    blocks, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        opening = lines[i].strip()
        if not opening.startswith("```"):
            i += 1
            continue
        above = next((line.strip() for line in reversed(lines[:i]) if line.strip()), "")
        marker = NOT_RUN.fullmatch(above)
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() == "```"), None)
        if end is None:
            raise ValueError(f"line {i + 1}: a fenced block that is never closed")
        blocks.append(Block(opening[3:].strip(), i + 2, "\n".join(lines[i + 1:end]) + "\n",
                            marker.group(1).strip() if marker else None))
        i = end + 1
    return blocks


def readme_blocks() -> list[Block]:
    return fenced_blocks(README.read_text())


def commands(block: Block) -> list[str]:
    """A shell block's commands, comments and blank lines dropped."""
    return [line.split("#", 1)[0].strip() for line in block.code.splitlines() if line.split("#", 1)[0].strip()]


def test_fenced_blocks_are_read_with_their_not_run_reasons():
    text = ("# t\n\n<!-- not run: a server -->\n```bash\nserve\n```\n\n```python\nx = 1\n```\n"
            "<!-- not run: -->\n\n```sh\nls\n```\n")
    assert fenced_blocks(text) == [Block("bash", 5, "serve\n", "a server"), Block("python", 9, "x = 1\n", None),
                                   Block("sh", 14, "ls\n", "")]
    with pytest.raises(ValueError, match="line 1: a fenced block that is never closed"):
        fenced_blocks("```python\nx = 1\n")


def test_the_readme_opens_with_its_two_setup_commands_and_stays_short():
    text = README.read_text()
    assert len(text.splitlines()) <= MAX_LINES, f"README.md: {len(text.splitlines())} lines, at most {MAX_LINES}"
    first = readme_blocks()[0]
    assert first.language == "bash" and commands(first) == SETUP_COMMANDS
    assert first.not_run, "README.md: the set-up commands need their not-run marker (`make test` would run itself)"
    before = text[: text.index("```")]
    assert [line for line in before.splitlines() if line.strip() and not NOT_RUN.fullmatch(line.strip())] == \
        ["# CanonicalGS Fusion"], "README.md: only its title may come before the set-up commands"


def test_every_block_is_run_or_says_why_not():
    blocks = readme_blocks()
    for block in blocks:
        assert block.language in (PYTHON, *SHELL, *DRAWN), f"README.md:{block.line}: a ```{block.language} block " \
            "that the README test does not know how to run (give it a language, or a not-run marker)"
        assert block.not_run != "", f"README.md:{block.line}: a not-run marker without its reason"
    ran = [b.language for b in blocks if b.not_run is None]
    assert ran.count(PYTHON) >= 3 and sum(ran.count(s) for s in SHELL) >= 2  # the parser found the examples


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """The service as a reader starts it (``canonical serve``, no token), on a free port."""
    root = tmp_path_factory.mktemp("readme_service")
    proc = ServerProcess(root / "data", root / "server.log")
    proc.start()
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def checkout(tmp_path_factory, shelf_dir, apc_bins_path) -> Path:
    """A scratch folder where the README's relative paths hold: ``.venv`` (this virtualenv, whose
    ``canonical`` is the installed console script) and ``../shared/data``."""
    root = tmp_path_factory.mktemp("readme_checkout")
    (root / "shared").symlink_to(DATA.parent, target_is_directory=True)
    (root / "repo").mkdir()
    (root / "repo" / ".venv").symlink_to(sys.prefix, target_is_directory=True)
    assert (root / "repo" / ".venv" / "bin" / "canonical").exists(), "the project is not installed in this virtualenv"
    return root / "repo"


def run_env(service: ServerProcess) -> dict:
    """The environment of the README's commands: the service's URL, this tree's code first (the
    installed package is this tree under `make test`), numba's cache where `make test` filled it."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CANONICAL_")}
    env.update(CANONICAL_URL=service.url, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")])))
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    return env


# Runs the blocks (JSON on stdin) in one namespace; a failure names the README line it came from.
RUNNER = """
import json, sys
namespace = {"__name__": "__main__"}
for line, code in json.load(sys.stdin):
    print(f"-- README.md:{line}", flush=True)
    exec(compile(code, f"README.md:{line}", "exec"), namespace)
"""


@pytest.mark.realdata
def test_the_readme_python_examples_run(service, checkout):
    blocks = [(b.line, b.code) for b in readme_blocks() if b.language == PYTHON and b.not_run is None]
    done = subprocess.run([sys.executable, "-c", RUNNER], input=json.dumps(blocks), cwd=checkout, env=run_env(service),
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, f"a README Python block failed:\n{done.stdout[-3000:]}\n{done.stderr[-5000:]}"


@pytest.mark.realdata
def test_the_readme_shell_examples_run(service, checkout):
    for block in (b for b in readme_blocks() if b.language in SHELL and b.not_run is None):
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", block.code], cwd=checkout, env=run_env(service),
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"README.md:{block.line}: the shell block failed ({done.returncode}):\n" \
                                     f"{done.stdout[-2000:]}\n{done.stderr[-5000:]}"
