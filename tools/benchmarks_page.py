"""``tools/BENCHMARKS.md``: the measured tables, each section written by the script that measures it.

Every benchmark script prints its side-by-side table and then calls :func:`refresh_section`,
which replaces that script's section of the page (between ``<!-- bench:KEY -->`` and
``<!-- /bench:KEY -->``) or appends it, leaving the other sections as they are.  Every row carries
the date it was measured, the machine and the code version (:func:`run_context`), so a table can
mix rows from several runs and still say where each figure comes from.  History stays in git.
"""

from __future__ import annotations

import datetime
import os
import platform
import re
import subprocess
from pathlib import Path

PAGE = Path(__file__).resolve().with_name("BENCHMARKS.md")
ROOT = Path(__file__).resolve().parents[1]
HEADER = """# Benchmarks

Measured on the machine each row names, by the scripts in `tools/`: each script runs graphsfm and
its peer (pycolmap's mappers) in the same run on the same input and refreshes its own section of
this page.  Times are wall-clock seconds; ratios compare the two sides of one run, since a shared
machine's speed drifts by tens of percent within minutes.  `code` is the git commit the graphsfm
side ran (`+changes`: with uncommitted changes to `sfm/`, `graph/` or `backend/`).
"""


def machine() -> str:
    """Cores, memory and processor of this machine, in a few words."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    try:
        mem_kb = int(next(ln for ln in Path("/proc/meminfo").read_text().splitlines()
                          if ln.startswith("MemTotal")).split()[1])
        memory = f", {mem_kb / 2**20:.0f} GB"
    except (OSError, StopIteration, ValueError):
        memory = ""
    return f"{cores} cores{memory}, {platform.machine()}"


def code_version() -> str:
    """The commit graphsfm's code is at (short hash), ``+changes`` when ``sfm/``, ``graph/`` or
    ``backend/`` differ from it; ``unknown`` outside a git checkout."""
    git = lambda *a: subprocess.run(["git", "-C", str(ROOT), *a], capture_output=True, text=True)  # noqa: E731
    head = git("rev-parse", "--short=7", "HEAD")
    if head.returncode != 0:
        return "unknown"
    dirty = git("status", "--porcelain", "--", "sfm", "graph", "backend").stdout.strip()
    return head.stdout.strip() + ("+changes" if dirty else "")


def run_context() -> dict:
    """``date``, ``machine`` and ``code`` columns for the rows of this run."""
    return {"date": datetime.date.today().isoformat(), "machine": machine(), "code": code_version()}


def markdown_table(rows: list[dict], keys: list[str] | None = None) -> str:
    keys = keys or list(dict.fromkeys(k for r in rows for k in r))
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(str(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def refresh_section(key: str, title: str, text: str, page: Path = PAGE) -> None:
    """Write ``## title`` and ``text`` (tables, the command that made them) as section ``key`` of
    ``page``, replacing the section's earlier content."""
    page = Path(page)
    body = page.read_text() if page.exists() else HEADER
    block = f"<!-- bench:{key} -->\n## {title}\n\n{text.strip()}\n<!-- /bench:{key} -->"
    pattern = re.compile(rf"<!-- bench:{re.escape(key)} -->.*?<!-- /bench:{re.escape(key)} -->", re.S)
    body = pattern.sub(lambda _: block, body) if pattern.search(body) else body.rstrip() + "\n\n" + block + "\n"
    tmp = page.with_name(page.name + ".tmp")
    tmp.write_text(body)
    tmp.replace(page)


def add_page_arguments(parser) -> None:
    """``--page PATH`` (default ``tools/BENCHMARKS.md``) and ``--no-page`` on a script's parser."""
    parser.add_argument("--page", type=Path, default=PAGE, help="the benchmarks page to refresh (default: %(default)s)")
    parser.add_argument("--no-page", action="store_true", help="print the table only; leave the page alone")


def publish(args, key: str, title: str, text: str) -> None:
    """Refresh section ``key`` of ``args.page`` with ``text`` and the command that made it,
    unless ``--no-page``."""
    if getattr(args, "no_page", False):
        return
    import shlex
    import sys

    command = "python tools/" + Path(sys.argv[0]).name + " " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    refresh_section(key, title, f"{text.strip()}\n\nMade by `{command.strip()}`.", args.page)
    print(f"refreshed section '{key}' of {args.page}")


def peer_version() -> str:
    """``pycolmap <version>``, the peer's code column."""
    import pycolmap

    return f"pycolmap {pycolmap.__version__}"
