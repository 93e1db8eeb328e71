"""tools/benchmarks_page.py: each benchmark refreshes its own section of the page, and every row
says when, where and on which code it was measured."""

from __future__ import annotations

import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from benchmarks_page import markdown_table, refresh_section, run_context


def test_a_section_is_replaced_in_place_and_the_others_are_kept(tmp_path):
    page = tmp_path / "BENCHMARKS.md"
    refresh_section("a", "First", "| x |\n|---|\n| 1 |", page)
    refresh_section("b", "Second", "two", page)
    refresh_section("a", "First again", "| x |\n|---|\n| 2 |", page)
    text = page.read_text()
    assert text.startswith("# Benchmarks")
    assert text.count("<!-- bench:a -->") == 1 and "| 2 |" in text and "| 1 |" not in text
    assert text.index("## First again") < text.index("## Second")  # the refreshed section stays where it was
    assert "two" in text


def test_rows_carry_date_machine_and_code():
    context = run_context()
    assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", context["date"])
    assert "cores" in context["machine"]
    assert re.fullmatch(r"[0-9a-f]{7}(\+changes)?|unknown", context["code"])
    table = markdown_table([{"method": "m", **context}])
    assert table.splitlines()[0] == "| method | date | machine | code |"
