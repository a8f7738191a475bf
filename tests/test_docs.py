"""The README and docs/ cannot drift from the measurements: every row of a figures table that names a
results file (a column headed "results file...") is checked against that JSON in
benchmarks/results/figures/, key by key, rounded as printed, and that folder holds exactly the files
the tables cite (the rest of a run's output is the experiment log, benchmarks/results/log/).  A README
headline may not be older than the code it measures by more than MAX_COMMITS_BEHIND commits (see
test_headlines_are_not_older_than_the_code_they_measure).  Also: the README stays a user's guide of at
most 20 KB with its pictures, CI's set-up and test commands, and working links."""
import json
import os
import re
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results", "figures")
DOCS = ["README.md", "DEVELOPERS.md"] + [os.path.join("docs", f) for f in sorted(os.listdir(os.path.join(ROOT, "docs")))
                                         if f.endswith(".md")]


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
    assert os.path.isfile(path), (f"{doc}: {figure!r} names {name}, which is not in benchmarks/results/figures/ "
                                  "(a cited figure's file moves there from benchmarks/results/log/)")
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


def test_the_figures_folder_holds_exactly_the_cited_files():
    """benchmarks/results/figures/ is what the docs cite; everything else a run wrote is the experiment
    log (benchmarks/results/log/)."""
    cited = {parse_source(r.values[3])[0] for r in ROWS}
    there = {f for f in os.listdir(RESULTS) if f.endswith(".json")}
    assert not cited - there, f"cited but not in benchmarks/results/figures/: {sorted(cited - there)}"
    assert not there - cited, (f"in benchmarks/results/figures/ but cited by no figures table (move them to "
                               f"benchmarks/results/log/): {sorted(there - cited)}")


# --- how old a headline may be ---------------------------------------------------------------------------
# A README headline's age is the number of commits that changed the code it measures (HEADLINE_CODE) since
# it was measured: since the commit its machine record names ("machine.commit", written by
# benchmarks/_results.write_results), or, for files written before the record existed, since the last
# commit that added or changed the results file (git log --follow, renames not counted).  A headline
# older than MAX_COMMITS_BEHIND is stale: it must be marked "†" in the README (the table's footnote says
# what that means) and listed in STALE with the re-measurement that refreshes it, so that the rule holds
# on a fresh clone while the figures wait for a quiet machine.  A file written before the record existed
# may be marked stale earlier (code changed that only a re-measurement can clear, e.g. on a GPU); a
# re-measured file (one with a machine record) within the limit must lose its mark and entry.  A new
# headline must say here which code it measures.
MAX_COMMITS_BEHIND = 30

_FIELD = ["neumesh_core/field", "neumesh_core/sampling", "neumesh_core/render", "neumesh_core/kernels"]
_TRAIN = _FIELD + ["neumesh_core/train"]
_FIT = _TRAIN + ["neumesh_core/data", "neumesh_core/reconstruct", "neumesh_core/evaluate.py", "neumesh_core/metrics.py"]
HEADLINE_CODE = {
    "fit_lego.json": _FIT,
    "fit_lego_cuda_h100_16min.json": _FIT,
    "fit_scan24_pyr3_3m_avg02.json": _FIT,
    "fit_scan24_pyr3_3m_avg02_seed1.json": _FIT,
    "core_default_scene_v1.json": _TRAIN + ["neumesh_core/data/synthetic"],
    "addon.json": _FIELD + ["addon/render", "addon/scene"],
    "render_lego.json": _FIELD,
    "render_gpu_lego.json": _FIELD,
    "docs_images.json": _TRAIN + ["neumesh_core/data/synthetic", "neumesh_core/evaluate.py", "neumesh_core/metrics.py"],
    "edit_lego_scaffold.json": ["neumesh_core/field", "neumesh_core/edit/swap.py", "neumesh_core/edit/align.py",
                                "neumesh_core/edit/transfer.py", "neumesh_core/edit/fit_check.py"],
    "paint_lego.json": _FIELD + ["neumesh_core/edit/paint.py", "neumesh_core/edit/paint_view.py"],
    "bake_lego.json": _FIELD + ["neumesh_core/bake"],
    "real_fox_ds2_30min_support8.json": _FIT + ["neumesh_core/fit.py"],
    "semantics_multipart.json": _TRAIN + ["neumesh_core/semantics"],
}
# stale headlines: the re-measurement that refreshes each (the commands are under the README's table)
STALE = {
    "fit_lego_cuda_h100_16min.json": "lego on a GPU, 16 minutes (command 2; a lent GPU)",
    "fit_scan24_pyr3_3m_avg02.json": "DTU scan24, 120 minutes (command 3)",
    "fit_scan24_pyr3_3m_avg02_seed1.json": "DTU scan24 with --seed 1 (command 3)",
    # the GPU kernels among the changes (restructured; not timed on a GPU since)
    "render_gpu_lego.json": "lego render speed on a GPU (command 12; a lent GPU)",
}
STALE_MARK = "†"


def _git(*args):
    try:
        run = subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    return run.stdout.strip() if run.returncode == 0 else None


def recorded_commit(name: str):
    """The commit a figures file's machine record names (None for files written before the record)."""
    with open(os.path.join(RESULTS, name), encoding="utf-8") as fh:
        machine = json.load(fh).get("machine")
    return machine.get("commit") if isinstance(machine, dict) else None   # older files: a note, or nothing


def measured_commit(name: str):
    """The commit a figures file was measured on: its machine record's, else the last commit that added
    or changed it (renames followed, not counted); None for a file git does not know yet (new: fresh)."""
    commit = recorded_commit(name)
    if commit and _git("cat-file", "-e", f"{commit}^{{commit}}") is not None:
        return commit
    rel = os.path.relpath(os.path.join(RESULTS, name), ROOT)
    return _git("log", "-1", "--follow", "--diff-filter=AM", "--format=%H", "--", rel) or None


def commits_behind(name: str) -> int:
    """Commits since the measurement that changed the code the headline measures."""
    commit = measured_commit(name)
    if commit is None:
        return 0
    return int(_git("rev-list", "--count", f"{commit}..HEAD", "--", *HEADLINE_CODE[name]))


def _history_or_skip():
    if _git("rev-parse", "--is-inside-work-tree") != "true":
        pytest.skip("not a git checkout: a headline's age needs the history")
    if _git("rev-parse", "--is-shallow-repository") == "true":
        pytest.skip("a shallow clone: a headline's age needs the full history (git fetch --unshallow)")


README_ROWS = [r for r in ROWS if r.values[0] == "README.md"]


@pytest.mark.parametrize("doc,figure,value,source", README_ROWS)
def test_headlines_are_not_older_than_the_code_they_measure(doc, figure, value, source):
    _history_or_skip()
    name = parse_source(source)[0]
    assert name in HEADLINE_CODE, (f"README headline {figure!r} ({name}): add the code it measures to "
                                   "HEADLINE_CODE in tests/test_docs.py")
    behind = commits_behind(name)
    marked = figure.endswith(STALE_MARK)
    assert marked == (name in STALE), (f"README headline {figure!r}: its {STALE_MARK} and its STALE entry in "
                                       "tests/test_docs.py go together")
    if behind > MAX_COMMITS_BEHIND:
        assert marked, (f"README headline {figure!r}: {name} is {behind} commits behind the code it measures "
                        f"(more than {MAX_COMMITS_BEHIND}): re-measure it, or mark it stale ({STALE_MARK} after "
                        "the figure, an entry in STALE) until it is re-measured")
    elif marked:
        assert recorded_commit(name) is None, (
            f"README headline {figure!r}: {name} was re-measured ({behind} commits behind, within "
            f"{MAX_COMMITS_BEHIND}): remove its {STALE_MARK} and its STALE entry")


def test_the_age_rule_sees_the_history(tmp_path, monkeypatch):
    """commits_behind counts the commits that touch the measured paths since the machine record's commit,
    falls back on git for a file without a record, and calls a file git does not know fresh."""
    _history_or_skip()
    first = _git("rev-list", "--max-parents=0", "HEAD").splitlines()[0]
    monkeypatch.setitem(globals(), "RESULTS", str(tmp_path))
    monkeypatch.setitem(HEADLINE_CODE, "old.json", ["neumesh_core"])
    monkeypatch.setitem(HEADLINE_CODE, "new.json", ["neumesh_core"])
    (tmp_path / "old.json").write_text(json.dumps({"machine": {"commit": first}}))
    (tmp_path / "new.json").write_text(json.dumps({"machine": "a note, no record"}))
    everything = int(_git("rev-list", "--count", f"{first}..HEAD", "--", "neumesh_core"))
    assert commits_behind("old.json") == everything > MAX_COMMITS_BEHIND
    assert recorded_commit("new.json") is None and commits_behind("new.json") == 0
    assert STALE_MARK not in "".join(r.values[2] for r in README_ROWS)   # the mark never hides in a value
    assert set(STALE) <= set(HEADLINE_CODE)


RENDER_ARGS = ("-f", "-a", "--render-frame", "--render-anim")
OUTPUT_ARGS = ("-o", "-E", "-F", "--render-output", "--engine", "--render-format")


def late_output_args(command: str) -> list:
    """The output options (-o, -E, -F) a `blender` command line gives after it renders (-f, -a):
    Blender reads its arguments in order, so they do not apply to that render."""
    toks = command.split()
    at = next((i for i, t in enumerate(toks) if t in RENDER_ARGS), None)
    return [] if at is None else [t for t in toks[at:] if t in OUTPUT_ARGS]


def test_blender_commands_in_the_docs_name_the_output_before_the_render():
    assert late_output_args("blender -b f.blend -E NEUMESH -f 1 -o //out/####") == ["-o"]
    assert late_output_args("blender -b f.blend -a -E NEUMESH") == ["-E"]
    assert late_output_args("blender -b f.blend -E NEUMESH -o //out/#### -f 1") == []
    bad = []
    for doc in DOCS:
        for n, line in enumerate(_read(doc).splitlines(), 1):
            for command in re.findall(r"\bblender\s+-[^`\n]*", line):
                if late_output_args(command):
                    bad.append(f"{doc}:{n}: {command.strip()}")
    assert not bad, "put -o/-E/-F before -f/-a (Blender reads its arguments in order):\n" + "\n".join(bad)
