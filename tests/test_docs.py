"""The documentation stays true: its Python code blocks and tutorials run.

* Every ```python block of ``docs/**/*.md`` and of the README runs.  The blocks of one page run
  in order in one fresh Python process (a page is read like a notebook: later
  blocks see the names of earlier ones), in a temporary directory holding a
  copy of ``scenes/``; the code keeps its Markdown line numbers, so a failure's
  traceback names ``docs/PAGE.md`` and the line.
* Markers, an HTML comment on the line before a block:
  ``<!-- docs-test: skip (why) -->`` for a block that needs data you do not
  have (your own capture); ``<!-- docs-test: slow -->`` for one that takes
  minutes (run with ``FMBRDF_DOCS_SLOW=1``).
* Every tutorial ``docs/tutorials/*.py`` runs (they assert their results).
* The plugin's docstring, which the BSDF reference page renders, lists every
  parameter with its default and range (``fmbrdf_mi/params.py``).
"""
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FENCE = re.compile(r"^(`{3,})\s*(\{code-block\}\s*)?python\s*$")
MARKER = re.compile(r"^<!--\s*docs-test:\s*(skip|slow)\b(.*?)-->\s*$")
SLOW = os.environ.get("FMBRDF_DOCS_SLOW") == "1"


def python_blocks(path):
    """[(first line number (1-based) of the code, code, marker or None)] of a Markdown file."""
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m:
            close = m.group(1)
            marker = None
            for back in range(i - 1, -1, -1):    # the marker: the last non-blank line before the fence
                if lines[back].strip():
                    mm = MARKER.match(lines[back].strip())
                    marker = mm.group(1) if mm else None
                    break
            j = i + 1
            while j < len(lines) and not lines[j].startswith(close):
                j += 1
            body = lines[i + 1:j]
            while body and body[0].startswith(":"):   # {code-block} options
                body = body[1:]
            start = j - len(body) + 1
            blocks.append((start, "\n".join(body), marker))
            i = j + 1
        else:
            i += 1
    return blocks


def page_script(path):
    """The page's runnable blocks as one script whose lines sit at their Markdown line numbers."""
    out, skipped = [], []
    for start, code, marker in python_blocks(path):
        if marker == "skip" or (marker == "slow" and not SLOW):
            skipped.append(start)
            continue
        out.extend([""] * (start - 1 - len(out)))
        out.extend(code.splitlines())
    return "\n".join(out) + "\n", skipped


PAGES = [ROOT / "README.md"] + sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts and python_blocks(p))
TUTORIALS = sorted((DOCS / "tutorials").glob("*.py"))


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env.setdefault("MPLBACKEND", "Agg")
    return env


def run_python(args, cwd, timeout=600):
    return subprocess.run([sys.executable, *args], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def test_the_docs_have_code_and_tutorials():
    """The runner finds what it should (a wrong fence pattern would make every page pass)."""
    names = {p.relative_to(ROOT).as_posix() for p in PAGES}
    assert {"README.md", "docs/getting-started.md", "docs/bsdf.md", "docs/howto/render.md", "docs/howto/fit.md",
            "docs/howto/dataset.md"} <= names
    assert {t.name for t in TUTORIALS} >= {"differentiable_rendering.py", "raw_capture_fit.py"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_page_code_blocks_run(page, tmp_path):
    script, skipped = page_script(page)
    rel = page.relative_to(ROOT).as_posix()
    shutil.copytree(ROOT / "scenes", tmp_path / "scenes")
    runner = tmp_path / "_run_page.py"
    runner.write_text(f"import sys\nsrc = open({str(tmp_path / '_page.py')!r}).read()\n"
                      f"exec(compile(src, {rel!r}, 'exec'), {{'__name__': '__main__'}})\n")
    (tmp_path / "_page.py").write_text(script)
    res = run_python([str(runner)], cwd=tmp_path)
    assert res.returncode == 0, (f"a Python block of {rel} failed (line numbers are the page's; "
                                 f"skipped blocks at lines {skipped}):\n{res.stdout[-3000:]}\n{res.stderr[-6000:]}")


@pytest.mark.parametrize("script", TUTORIALS, ids=lambda p: p.name)
def test_tutorial_runs(script, tmp_path):
    res = run_python([str(script), str(tmp_path / "out")], cwd=tmp_path)
    assert res.returncode == 0, f"{script.name} failed:\n{res.stdout[-3000:]}\n{res.stderr[-6000:]}"


def test_plugin_docstring_lists_every_parameter():
    """The BSDF reference page is the plugin's docstring: it must carry every parameter's
    name, default and valid range as fmbrdf_mi/params.py defines them."""
    sys.path.insert(0, str(DOCS / "_ext"))
    try:
        from plugin_docs_source import plugin_doc   # (no docutils: the test extras suffice)
    finally:
        sys.path.pop(0)
    from fmbrdf_mi import params as P

    doc = plugin_doc("fmbrdf")
    rows = {}
    for block in re.split(r"\n\s*\* - ", doc)[1:]:
        cells = [c.strip() for c in re.split(r"\n\s*- ", block)]
        rows[cells[0]] = cells
    for name, (default, lo, hi, lo_incl, _) in P.SCALAR_PARAMS.items():
        row = rows[f"``{name}``"]
        assert float(row[2]) == default, (name, row)
        lo_s = f"{lo:g}" if lo != 0.01 else "0.01"
        hi_s = "π/2" if abs(hi - 0.5 * 3.141592653589793) < 1e-12 else f"{hi:g}"
        assert row[3] == f"{'[' if lo_incl else '('}{lo_s}, {hi_s}]", (name, row)
    assert rows["``k_s``"][2] == f"{P.DEFAULT_K_S}"
    assert rows["``r_k`` *or* ``k_b``"][2] == f"r_k = {P.DEFAULT_R_K}"
    assert "``tables``" in rows
