"""`python -m junction.analysis results-md`: every table of RESULTS.md, made again by the
commands RESULTS.md names (each fenced `sh` block that runs `python -m junction.analysis`),
so the file and the summaries cannot drift apart unnoticed (python/tests/test_analysis.py
checks that each table RESULTS.md prints is what its command prints)."""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[3]
PREFIX = "PYTHONPATH=python python3 -m junction.analysis "


def commands(text: str) -> list[tuple[str, list[str], list[str]]]:
    """(command, its arguments, the table lines that follow its block) per analysis command
    of a Markdown page, in order."""
    out = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() == "```sh":
            block = []
            i += 1
            while i < len(lines) and lines[i].strip() != "```":
                block.append(lines[i])
                i += 1
            joined = re.sub(r"\\\n\s*", " ", "\n".join(block))
            found = [l.strip() for l in joined.splitlines() if l.strip().startswith(PREFIX)]
            # The table rows after the block, up to the next heading or code block.
            rows = []
            j = i + 1
            while j < len(lines) and not lines[j].startswith(("#", "```")):
                if lines[j].startswith("|"):
                    rows.append(lines[j])
                j += 1
            for k, command in enumerate(found):
                # The rows belong to the block's last command.
                out.append((command, shlex.split(command[len(PREFIX):]),
                            rows if k == len(found) - 1 else []))
        i += 1
    return out


def run(argv: list[str], main: Callable[[list[str]], object]) -> str:
    """What `main(ARGV)` (the command line's entry, `cli.main`, handed in so this module does
    not import the command line that imports it) prints, run from the repository root."""
    buffer = io.StringIO()
    cwd = os.getcwd()
    try:
        os.chdir(ROOT)
        with contextlib.redirect_stdout(buffer):
            main(argv)
    finally:
        os.chdir(cwd)
    return buffer.getvalue()


def print_all(main: Callable[[list[str]], object], page: Path = ROOT / "RESULTS.md") -> None:
    for command, argv, _ in commands(page.read_text()):
        print(f"```sh\n{command}\n```\n")
        print(run(argv, main))
