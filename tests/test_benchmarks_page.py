"""docs/benchmarks.md is generated from the committed result file and agrees with it."""

from __future__ import annotations

import json
import subprocess
import sys

from benchmarks.markdown import render
from benchmarks.report import fmt_value, read_document
from tests.conftest import ROOT

RESULTS = ROOT / "benchmarks" / "results.json"
PAGE = ROOT / "docs" / "benchmarks.md"


def test_the_committed_page_is_the_page_of_the_committed_result_file():
    """Regenerating the page from the JSON gives the committed page byte for byte: an edit of
    either alone fails here."""
    doc = read_document(RESULTS)
    assert PAGE.read_text() == render(doc, source="benchmarks/results.json", target="docs/benchmarks.md")


def test_every_figure_of_the_file_is_a_row_of_its_section_and_the_machine_is_named():
    doc = read_document(RESULTS)
    page = PAGE.read_text()
    assert doc["figures"], "the result file holds no figures"
    for f in doc["figures"]:
        row = f"| {f['size']} | {f['label']} | {fmt_value(f['value'])}"
        assert row in page, row
    assert doc["git"]["commit"] in page and doc["created"] in page and doc["machine"]["cpu"] in page
    assert page.count("\n## ") >= len(set(doc["sections"])) + 1  # a table per benchmark, and the method


def test_the_one_command_writes_the_page_from_a_result_file(tmp_path):
    doc = read_document(RESULTS)
    doc["figures"][0]["value"] = 123456.0  # a changed figure shows in the page
    src = tmp_path / "r.json"
    src.write_text(json.dumps(doc))
    out = tmp_path / "docs" / "b.md"
    r = subprocess.run([sys.executable, "-m", "benchmarks", "--load", str(src), "--markdown", str(out)],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"| {fmt_value(123456.0)} " in out.read_text()
    assert out.read_text() == render(doc, source=str(src), target=str(out))


def test_a_bad_result_file_is_one_line_and_exit_status_2(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    r = subprocess.run([sys.executable, "-m", "benchmarks", "--load", str(bad), "--markdown", str(tmp_path / "b.md")],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "not a benchmark result file" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "b.md").exists()
