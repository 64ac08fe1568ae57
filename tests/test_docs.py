"""The generated op reference: committed pages are current, and the generator
itself (one page per op, knob tables with physical ranges, links that resolve,
determinism, drift/missing/stale detection)."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

import fsjax

REPO = Path(__file__).resolve().parents[1]


def _load_gen_docs():
    spec = importlib.util.spec_from_file_location("fsjax_tools_gen_docs", REPO / "tools" / "gen_docs.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up while the class is built
    spec.loader.exec_module(mod)
    return mod


gen = _load_gen_docs()
OPS = fsjax.list_ops()


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    root = tmp_path_factory.mktemp("docs_root")
    res = gen.write_docs(root)
    return root, res


def test_committed_docs_are_current():
    problems = gen.check_docs(REPO)
    assert not problems, (
        "generated docs are out of date (run `python tools/gen_docs.py`):\n  " + "\n  ".join(problems)
    )


def test_one_page_per_op_with_summary_signature_and_example(generated):
    root, res = generated
    assert not res.removed
    for s in OPS:
        page = root / "docs" / "ops" / s.family / f"{s.name}.md"
        assert page.is_file(), f"no page for {s.name}"
        text = page.read_text(encoding="utf-8")
        assert text.startswith(gen.BANNER)
        assert f"# `{s.name}`" in text
        assert s.summary in text
        assert f"`{s.signature_str()}`" in text
        assert gen.call_signature(s) in text
        assert "```pycon\n>>> " in text, f"{s.name}: example not rendered as a code block"
        assert f"| Differentiable | {'yes' if s.differentiable else 'no'} |" in text
        for ref in s.refs:
            assert f"- {ref}" in text
        for pname, default in s.params.items():
            assert f"| `{pname}` | keyword |" in text
            assert f"`{gen._cell(gen.fmt_value(default))}`" in text
    assert (root / "docs" / "ops" / "INDEX.md").is_file()
    assert (root / "docs" / "OP_CATALOG.md").is_file()


def test_knob_table_has_physical_ranges(generated):
    root, _ = generated
    with_knobs = [s for s in OPS if s.knobs]
    assert with_knobs
    for s in with_knobs:
        text = (root / "docs" / "ops" / s.family / f"{s.name}.md").read_text(encoding="utf-8")
        assert "| knob | parameter | mapping | range | unit |" in text
        for letter, (pname, k) in zip("ab", s.knobs.items(), strict=False):
            row = [ln for ln in text.splitlines() if ln.startswith(f"| `{letter}` | `{pname}` |")]
            assert len(row) == 1, f"{s.name}: no knob row for {letter}={pname}"
            assert f"[{k.lo:g}, {k.hi:g}]" in row[0]
            assert row[0].rstrip(" |").endswith(k.unit or "-")
            assert gen.knob_mapping(k)[0] in row[0]


def test_gaussian_page_concretely():
    text = gen.render_all()["docs/ops/filters/gaussian.md"]
    assert "| `a` | `sigma` | logarithmic (`p = lo (hi / lo)^u`) | [0.3, 8] | px |" in text
    assert "| `sigma` | keyword | `float` | `1.0` | `a` |" in text
    assert "gaussian(img: Image, /, *, sigma: float = 1.0, truncate: float = 4.0" in text


def test_index_and_catalog_list_every_op(generated):
    root, _ = generated
    index = (root / "docs" / "ops" / "INDEX.md").read_text(encoding="utf-8")
    catalog = (root / "docs" / "OP_CATALOG.md").read_text(encoding="utf-8")
    for fam in fsjax.families():
        assert f"\n## {fam}\n" in index
    for s in OPS:
        assert f"[`{s.name}`]({s.family}/{s.name}.md)" in index
        line = [ln for ln in catalog.splitlines() if ln.startswith(f"| [`{s.name}`](ops/{s.family}/{s.name}.md) |")]
        assert len(line) == 1, s.name
        assert f"| {s.family} | `{s.signature_str()}` |" in line[0]
    rows = [ln for ln in catalog.splitlines() if ln.startswith("| [`")]
    assert len(rows) == len(OPS)


def test_relative_links_resolve(generated):
    root, _ = generated
    link = re.compile(r"\]\(([^)#]+\.md)(?:#[\w-]+)?\)")
    n = 0
    for page in (root / "docs").rglob("*.md"):
        for target in link.findall(page.read_text(encoding="utf-8")):
            assert (page.parent / target).resolve().is_file(), f"{page.relative_to(root)} -> {target}"
            n += 1
    assert n > len(OPS)


def test_connects_to_lists_linear_successors_with_cap():
    img_op = fsjax.get_op("gaussian")
    nxt = gen.connects_to(img_op, OPS)
    assert nxt and all(s.linear and s.takes[0] is fsjax.Image for s in nxt)
    assert [s.name for s in nxt] == sorted(s.name for s in nxt)
    assert not any(s.n_inputs > 1 for s in nxt)
    sec = "\n".join(gen.connects_section(img_op, OPS, cap=3))
    assert sec.count("](") == 3
    assert f"{len(nxt)} single-input op(s)" in sec
    if len(nxt) > 3:
        assert f"... and {len(nxt) - 3} more" in sec
    full = "\n".join(gen.connects_section(img_op, OPS, cap=10_000))
    assert full.count("](") == len(nxt)


def test_output_is_deterministic_and_machine_free():
    a = gen.render_all()
    b = gen.render_all(list(reversed(OPS)))
    assert a == b
    for rel, text in a.items():
        assert not re.search(r"0x[0-9a-fA-F]{6,}", text), f"{rel}: object address"
        assert str(REPO) not in text and "/tmp/" not in text and "/home/" not in text, f"{rel}: machine path"
        assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text), f"{rel}: date"
        assert text.endswith("\n") and not text.endswith("\n\n")


def test_fmt_value_has_no_addresses():
    class Thing:
        pass

    out = gen.fmt_value(Thing())
    assert "0x" not in out and out == "<Thing>"
    assert gen.fmt_value((1, 2.5, "x", None)) == "(1, 2.5, 'x', None)"
    assert gen.fmt_value((3,)) == "(3,)"


def test_check_reports_drifted_missing_and_stale(tmp_path):
    assert gen.check_docs(tmp_path)  # empty tree: everything missing
    assert all(p.startswith("missing: ") for p in gen.check_docs(tmp_path))
    gen.write_docs(tmp_path)
    assert gen.check_docs(tmp_path) == []
    assert gen.main(["--check", "--root", str(tmp_path)]) == 0

    s = OPS[0]
    page = tmp_path / "docs" / "ops" / s.family / f"{s.name}.md"
    page.write_text(page.read_text(encoding="utf-8") + "edited\n", encoding="utf-8")
    other = OPS[-1]
    (tmp_path / "docs" / "ops" / other.family / f"{other.name}.md").unlink()
    ghost = tmp_path / "docs" / "ops" / "ghostfamily" / "removed_op.md"
    ghost.parent.mkdir(parents=True)
    ghost.write_text("old page\n", encoding="utf-8")

    problems = gen.check_docs(tmp_path)
    assert problems == sorted([
        f"drifted: docs/ops/{s.family}/{s.name}.md",
        f"missing: docs/ops/{other.family}/{other.name}.md",
        "stale: docs/ops/ghostfamily/removed_op.md",
    ])
    assert gen.main(["--check", "--root", str(tmp_path)]) == 1

    res = gen.write_docs(tmp_path)
    assert sorted(res.written) == sorted([f"docs/ops/{s.family}/{s.name}.md",
                                         f"docs/ops/{other.family}/{other.name}.md"])
    assert res.removed == ["docs/ops/ghostfamily/removed_op.md"]
    assert not ghost.parent.exists()
    assert gen.check_docs(tmp_path) == []
