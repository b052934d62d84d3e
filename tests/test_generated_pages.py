"""The generated pages are what their renderers make of the committed raw results.

docs/results.md (``twinfocus bench paper``) and docs/beyond.md (``twinfocus bench beyond``) are
written from the raw JSON files beside them; every figure on them is the renderer's reading of
those files. Each page is re-rendered here from copies of its committed raw files into a scratch
folder (no experiment runs) and compared with the committed page, so a hand edit, a renderer
change without a regenerated page, or a raw file changed without one fails. The tables other pages
quote from benchmark result files (``<!-- table: ... -->`` blocks, benchmarks/page_tables.py) are
rendered anew from those files and compared the same way.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from benchmarks import page_tables
from twinfocus.evaluation.beyond import write_beyond_report
from twinfocus.evaluation.report import write_report

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
_IMAGE = re.compile(r"!\[[^\]]*\]\(([^)]+\.png)\)")


def _copy_inputs(name: str, tmp: Path, extra: tuple[str, ...] = ()) -> Path:
    """A scratch ``tmp/NAME/`` holding copies of docs/NAME/raw/ and of the named files beside it,
    so that links from ``tmp/NAME.md`` read as those from docs/NAME.md."""
    out = tmp / name
    shutil.copytree(DOCS / name / "raw", out / "raw")
    for f in extra:
        shutil.copy(DOCS / name / f, out / f)
    return out


def _stale(page: Path) -> str:
    cmd = {"results": "paper", "beyond": "beyond"}[page.stem]
    return (
        f"{page.relative_to(ROOT)} is not what its raw results render to: run twinfocus bench {cmd} "
        f"--report-only --out docs/{page.stem} --markdown {page.relative_to(ROOT)}"
    )


@pytest.mark.slow  # 3.8 s (2 cores, idle): out of make test-fast (benchmarks/results/test_fast.json); the beyond page's check stays
def test_results_page_is_its_raw_results(tmp_path: Path) -> None:
    page = DOCS / "results.md"
    out = _copy_inputs("results", tmp_path, ("field_handheld.json", "field_twin.json"))
    md = write_report(out, tmp_path / "results.md")
    assert md.read_text(encoding="utf-8") == page.read_text(encoding="utf-8"), _stale(page)
    assert json.loads((out / "summary.json").read_text()) == json.loads((DOCS / "results" / "summary.json").read_text())
    # every figure the page shows is one the renderer draws, and is committed beside it
    linked = set(_IMAGE.findall(page.read_text(encoding="utf-8")))
    assert linked and linked == {f"results/{p.name}" for p in out.glob("*.png")}
    assert all((DOCS / rel).is_file() for rel in linked)


def test_beyond_page_is_its_raw_results(tmp_path: Path) -> None:
    page = DOCS / "beyond.md"
    out = _copy_inputs("beyond", tmp_path)
    md = write_beyond_report(out, tmp_path / "beyond.md")
    assert md.read_text(encoding="utf-8") == page.read_text(encoding="utf-8"), _stale(page)
    assert json.loads((out / "summary.json").read_text()) == json.loads((DOCS / "beyond" / "summary.json").read_text())


def test_generated_pages_say_so_first() -> None:
    for name, suite in (("results", "paper"), ("beyond", "beyond")):
        head = "\n".join((DOCS / f"{name}.md").read_text(encoding="utf-8").splitlines()[:3])
        assert f"generated from the raw results in docs/{name}/raw/ by `twinfocus bench {suite} --report-only" in head


def test_a_changed_raw_figure_makes_the_page_stale(tmp_path: Path) -> None:
    out = _copy_inputs("beyond", tmp_path)
    raw = out / "raw" / "beyond_error.json"
    doc = json.loads(raw.read_text())
    doc["records"][0]["ssim"] = 0.0  # one draw of "no correction", in the page's first table
    raw.write_text(json.dumps(doc))
    page = (DOCS / "beyond.md").read_text(encoding="utf-8")
    assert write_beyond_report(out, tmp_path / "beyond.md").read_text(encoding="utf-8") != page


# --- tables a page quotes from a result file (benchmarks/page_tables.py) ----------------------------


@pytest.mark.parametrize("page", page_tables.pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_a_pages_tables_are_their_files(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    assert page_tables.render_page(text) == text, (
        f"a table of {page.relative_to(ROOT)} is not what its file holds: run python -m benchmarks.page_tables"
    )


def test_pages_have_generated_tables() -> None:
    assert len(page_tables.pages()) >= 3


def test_the_lookup_summarises_records() -> None:
    rows = [{"s": "a", "v": 1.0, "n": {"x": -3.0}}, {"s": "a", "v": 3.0, "n": {"x": 1.0}}, {"s": "b", "v": 8.0}]
    data = {"cond 1": rows}
    assert page_tables.lookup(data, "cond%201.where(s=a).mean(v)") == 2.0
    assert page_tables.lookup(data, "cond%201.where(s=a).sd(v)") == 1.0  # ddof 0
    assert page_tables.lookup(data, "cond%201.mean(n.x)") == -1.0  # the record without it left out
    assert page_tables.lookup(data, "cond%201.absmax(n.x)") == 3.0
    assert page_tables.lookup(data, "cond%201.n(n.x)") == 2
    assert page_tables.lookup(data, "cond%201.median(v)") == 3.0
    with pytest.raises(KeyError):
        page_tables.lookup(data, "cond%201.where(s=c).mean(v)")


def test_a_table_block_fills_its_template_per_row(tmp_path: Path) -> None:
    (tmp_path / "r.json").write_text(json.dumps({"x": [{"v": 0.5}, {"v": 0.7}], "y": [{"v": 0.25}]}))
    page = (
        "text\n<!-- table: r.json\nfirst = #x\nsecond = r.json#y\n| {label} | {v|msd} | {n(v)} | {max(v):.1f} |\n-->\n"
        "| row | v | n | max |\n|---|---|---|---|\n| stale | 1 | 2 | 3 |\n\n<!-- /table -->\nmore text\n"
    )
    out = page_tables.render_page(page, tmp_path)
    assert "| first | 0.600 ± 0.100 | 2 | 0.7 |\n| second | 0.250 ± 0.000 | 1 | 0.2 |\n" in out
    assert "| row | v | n | max |\n|---|---|---|---|\n| first" in out and "stale" not in out
    assert out.startswith("text\n<!-- table: r.json\n") and out.endswith("\n<!-- /table -->\nmore text\n")
    assert page_tables.render_page(out, tmp_path) == out


def test_a_table_block_reads_other_files_and_compares_fields(tmp_path: Path) -> None:
    rows = [{"a": 0.5, "b": 0.6, "ok": True}, {"a": 0.5, "b": 0.501, "ok": False}, {"a": 0.5, "b": 0.4, "ok": False}]
    (tmp_path / "r.json").write_text(json.dumps({"x, one": rows, "y": rows[:1]}))
    (tmp_path / "s.json").write_text(json.dumps({"x, one": [{"c": 2.0}], "y": [{"c": 4.0}], "top": {"y": 7}}))
    page = (
        "<!-- table: r.json\n{} = : x, one; y\n"
        "| {label} | {where(b>a+0.005).n(b)} / {where(b<a-0.005).n(b)} | {where(ok=True).mean(b)} | "
        "{where(ok=False,b<0.45).n(b)} | {s.json>mean(c):.1f} | {s.json#top.$?-} | {mean(zz)?none} |\n-->\n"
        "| row | up / down | trusted | low | c | top | zz |\n|---|---|---|---|---|---|---|\n\n<!-- /table -->\n"
    )
    out = page_tables.render_page(page, tmp_path)
    assert "| x, one | 1 / 1 | 0.600 | 1 | 2.0 | - | none |\n| y | 1 / 0 | 0.600 | 0 | 4.0 | 7 | none |\n" in out


def test_the_family_trust_summary_is_what_its_records_give() -> None:
    """dtwin_family_trust.json (``bench_dtwin_family --trust-summary``, which docs/digital_twin_confidence.md's
    false-trust tables read) is the confidence report's present rules over the committed records."""
    from benchmarks.bench_dtwin_family import trust_rows

    results = ROOT / "benchmarks" / "results"
    committed = json.loads((results / "dtwin_family_trust.json").read_text())
    for name, file in (("bench", "dtwin_family.json"), ("held out", "dtwin_family_heldout.json")):
        fresh = json.loads(json.dumps(trust_rows(json.loads((results / file).read_text()))))
        assert fresh == committed[name], f"stale: run python -m benchmarks.bench_dtwin_family --trust-summary ({name})"
        both = committed[f"{name}, both twins"]
        twins = [r for r in fresh if r["twin"] in ("digital", "physical")]
        assert both["false_trust"] == sum(r["false_trust"] for r in twins)
        assert both["false_alarm_pct"] == pytest.approx(100 * both["false_alarm"] / both["results"])


def test_the_results_pages_field_files_are_the_benchmarks() -> None:
    """docs/results.md's field section reads copies beside its raw results: they are the benchmark
    files the field pages quote (docs/handheld.md, docs/digital_twin_autofocus.md), byte for byte."""
    for copy, source in (("field_handheld.json", "handheld.json"), ("field_twin.json", "field_twin.json")):
        assert (DOCS / "results" / copy).read_bytes() == (ROOT / "benchmarks" / "results" / source).read_bytes(), (
            f"copy benchmarks/results/{source} to docs/results/{copy} and rerun twinfocus bench paper --report-only"
        )
