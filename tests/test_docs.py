"""The user docs hold what they promise: the README is short and its pictures and links exist,
no product page names an issue number, and docs/results.md is what scripts/results.py makes of
the benchmark's JSON (a hand edit or a new bench run without regenerating fails here)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PRODUCT_DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def _results_module():
    spec = importlib.util.spec_from_file_location("results", REPO / "scripts" / "results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_is_short():
    n = len((REPO / "README.md").read_text().splitlines())
    assert n < 200, f"README.md has {n} lines"


def test_links_and_pictures_exist():
    link = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
    for page in PRODUCT_DOCS:
        for target in link.findall(page.read_text()):
            if "://" in target:
                continue
            assert (page.parent / target).exists(), f"{page.name} links to missing {target}"


def test_no_issue_numbers_in_product_docs():
    pat = re.compile(r"\bissues? #?\d+|#\d{1,4}\b", re.I)
    for page in PRODUCT_DOCS:
        for i, line in enumerate(page.read_text().splitlines(), 1):
            assert not pat.search(line), f"{page.name}:{i}: {line.strip()}"


def test_results_page_is_generated_from_the_bench_json():
    mod = _results_module()
    assert (REPO / "docs" / "results.md").read_text() == mod.render(), (
        "docs/results.md is stale: run python scripts/results.py"
    )


def test_results_page_follows_the_json(tmp_path):
    """The generator reads the figures from the JSON (a changed number changes the page) and
    leaves out what a run did not write."""
    import json
    import shutil

    mod = _results_module()
    src = REPO / "docs" / "bench" / "accuracy.json"
    acc = json.loads(src.read_text())
    row = next(r for r in acc["rows"] if r["name"] == "cfsr" and not r["scene"].startswith("reds"))
    row["psnr_all"] = 99.125
    (tmp_path / "accuracy.json").write_text(json.dumps(acc))
    page = mod.render(tmp_path)
    assert "**99.12 / " in page
    assert "## Throughput" not in page and "## Cost follows the scene" not in page
    shutil.copy(REPO / "docs" / "bench" / "sweep.json", tmp_path / "sweep.json")
    assert "## Cost follows the scene" in mod.render(tmp_path)
