"""The README and docs/ cannot drift from the measurements: every row of a figures table that names a
results file (a column headed "results file...") is checked against that JSON in benchmarks/results/,
key by key, rounded as printed.  Also: the README stays a user's guide of at most 20 KB with its
pictures, CI's set-up and test commands, and working links."""
import json
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
DOCS = ["README.md", "DEVELOPERS.md", os.path.join("docs", "benchmarks.md"), os.path.join("docs", "baking.md"),
        os.path.join("docs", "real_captures.md")]


def _read(rel):
    with open(os.path.join(ROOT, rel), encoding="utf-8") as fh:
        return fh.read()


def _cells(line):
    # split a table row on unescaped pipes (`a\|b` inside a cell is one cell)
    return [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]


def figure_rows(text):
    """(figure, value cell, results cell) of every table row under a header with a 'results file' column."""
    rows, col = [], None
    for line in text.splitlines():
        if not line.startswith("|"):
            col = None
            continue
        cells = _cells(line)
        if col is None:
            heads = [c.lower() for c in cells]
            col = next((i for i, h in enumerate(heads) if h.startswith("results file")), -1)
            vcol = heads.index("value") if "value" in heads else -1
            if col < 0 or vcol < 0:
                col = -1
            continue
        if col < 0 or set(line.replace("|", "").strip()) <= set("-: "):
            continue
        rows.append((cells[0], cells[vcol], cells[col]))
    return rows


def lookup(data, path):
    for part in re.findall(r"\[\d+\]|[^.\[\]]+", path):
        data = data[int(part[1:-1])] if part.startswith("[") else data[part]
    return data


def parse_source(cell):
    """'`file.json`: `a.b` / `c[0].d`' -> ('file.json', ['a.b', 'c[0].d'])"""
    ticks = re.findall(r"`([^`]+)`", cell)
    assert ticks and ticks[0].endswith(".json"), f"results cell must start with `<file>.json`: {cell!r}"
    return ticks[0], ticks[1:]


def _all_rows():
    out = []
    for doc in DOCS:
        for fig, value, source in figure_rows(_read(doc)):
            out.append(pytest.param(doc, fig, value, source, id=f"{os.path.basename(doc)}: {fig[:50]}"))
    return out


ROWS = _all_rows()


def test_the_readme_has_a_headline_table_with_the_main_figures():
    readme = [r for r in ROWS if r.values[0] == "README.md"]
    assert len(readme) >= 5
    files = {parse_source(r.values[3])[0] for r in readme}
    assert {"fit_lego.json", "fit_scan24_pyr3_3m_avg02.json", "core_default_scene_v1.json",
            "semantics_multipart.json"} <= files


@pytest.mark.parametrize("doc,figure,value,source", ROWS)
def test_figure_matches_its_results_file(doc, figure, value, source):
    name, keys = parse_source(source)
    path = os.path.join(RESULTS, name)
    assert os.path.isfile(path), f"{doc}: {figure!r} names {name}, which is not in benchmarks/results/"
    with open(path, encoding="utf-8") as fh:
        data = json.load(fh)
    printed = re.findall(r"\d+(?:\.\d+)?", value)
    assert keys and len(printed) == len(keys), (
        f"{doc}: {figure!r}: {len(printed)} figures ({value!r}) for {len(keys)} keys ({keys})")
    for text, key in zip(printed, keys):
        got = lookup(data, key)
        decimals = len(text.split(".")[1]) if "." in text else 0
        assert f"{float(got):.{decimals}f}" == text, (
            f"{doc}: {figure!r}: printed {text}, but {name} {key} = {got}")


def test_parsers():
    assert lookup({"a": [{"b": 1.5}]}, "a[0].b") == 1.5
    assert parse_source("`x.json`: `a.b` / `c[1].d`") == ("x.json", ["a.b", "c[1].d"])
    table = "| figure | value | results file: key |\n|---|---|---|\n| f | 1.25 / 3 | `x.json`: `a` / `b` |\n"
    assert figure_rows(table) == [("f", "1.25 / 3", "`x.json`: `a` / `b`")]


def test_readme_is_a_short_users_guide():
    text = _read("README.md")
    assert len(text.encode("utf-8")) <= 20000
    # CI (.ci/run) runs the README's set-up and test commands
    assert "./setup.sh" in text and ".venv/bin/python -m pytest -q" in text
    ci = _read(os.path.join(".ci", "run"))
    assert "./setup.sh" in ci and ".venv/bin/python -m pytest -q" in ci
    assert "## Layout" not in text  # the module map lives in DEVELOPERS.md
    assert len(re.findall(r"!\[[^\]]*\]\([^)]+\.png\)", text)) >= 4
    for section in ("## Quick start", "## In Blender", "## Command line", "## Python API", "## Headline figures",
                    "## Limitations", "## License and data"):
        assert section in text


@pytest.mark.parametrize("doc", ["README.md", "DEVELOPERS.md"] + [os.path.join("docs", f) for f in
                                                                  sorted(os.listdir(os.path.join(ROOT, "docs")))
                                                                  if f.endswith(".md")])
def test_links_to_documents_resolve(doc):
    """Links to files (not pictures, which scripts make: scripts/make_docs_images.py,
    scripts/edit_pictures.py) point at files that exist."""
    base = os.path.dirname(os.path.join(ROOT, doc))
    for target in re.findall(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)", _read(doc)):
        if re.match(r"[a-z]+://", target) or target.startswith("#") or target.endswith(".png"):
            continue
        path = target.split("#")[0]
        assert os.path.exists(os.path.join(base, path)), f"{doc}: broken link {target}"
