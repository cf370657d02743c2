"""The documentation stays true: its Python code blocks, shell commands and tutorials run.

* Every ```python block of ``docs/**/*.md`` and of the README runs.  The blocks of one page run
  in order in one fresh Python process (a page is read like a notebook: later
  blocks see the names of earlier ones), in a temporary directory holding a
  copy of ``scenes/``; the code keeps its Markdown line numbers, so a failure's
  traceback names ``docs/PAGE.md`` and the line.
* Every ```bash / ```sh / ```console block of ``docs/**/*.md`` and of the README
  runs as written (``console``: the lines after ``$ ``), in order, each block in
  ``bash -e -o pipefail`` under a time limit, in a temporary directory holding the
  example data (``fmbrdf-mi example-data``: :mod:`fmbrdf_mi.synthetic.examples`),
  a copy of ``scenes/`` and ``tools/``, with ``fmbrdf-mi`` and ``python`` this
  interpreter; the repository's files must be unchanged afterwards (no docs
  command writes into the repository).
* Markers, an HTML comment on the line before a block (either kind):
  ``<!-- docs-test: skip (why) -->`` for a block that needs data you do not
  have (your own capture), a GPU, or hours; ``<!-- docs-test: slow -->`` for one that takes
  minutes (run with ``FMBRDF_DOCS_SLOW=1``); the shell blocks of the pages outside
  ``QUICK_SHELL_PAGES`` run only with ``FMBRDF_DOCS_SLOW=1`` too.
* Every tutorial ``docs/tutorials/*.py`` runs (they assert their results).
* The plugin's docstring, which the BSDF reference page renders, lists every
  parameter with its default and range (``fmbrdf_mi/params.py``).
"""
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
FENCE = re.compile(r"^(`{3,})\s*(\{code-block\}\s*)?python\s*$")
SHELL_FENCE = re.compile(r"^(`{3,})\s*(\{code-block\}\s*)?(bash|sh|console)\s*$")
MARKER = re.compile(r"^<!--\s*docs-test:\s*(skip|slow)\b(.*?)-->\s*$")
SLOW = os.environ.get("FMBRDF_DOCS_SLOW") == "1"


#: Seconds one shell block may take.
SHELL_BLOCK_TIMEOUT = 900
# The pages whose shell blocks run in every test run; the others' commands take minutes (fits of several
# images, textured and colour captures, the how-tos' fits) and run with FMBRDF_DOCS_SLOW=1 (CI's time).
QUICK_SHELL_PAGES = {"docs/howto/render.md", "docs/howto/dataset.md"}


def python_blocks(path, fence=FENCE):
    """[(first line number (1-based) of the code, code, marker or None)] of a Markdown file's blocks
    whose opening line matches ``fence``."""
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        m = fence.match(lines[i])
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
            if m.group(m.re.groups) == "console":       # the commands: the lines after the prompt
                body = [b[2:] if b.startswith("$ ") else "" for b in body]
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
SHELL_PAGES = [p for p in [ROOT / "README.md"] + sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.parts)
               if python_blocks(p, SHELL_FENCE)]
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


def shell_blocks(path):
    """[(line, code, marker)] of a page's shell blocks."""
    return python_blocks(path, SHELL_FENCE)


def repo_state():
    """What ``git status`` says of the repository's files (None outside a git checkout)."""
    try:
        res = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=all"],
                             capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return res.stdout if res.returncode == 0 else None


@pytest.fixture(scope="session")
def example_data(tmp_path_factory):
    """The example data, made once by the command the docs name."""
    out = tmp_path_factory.mktemp("example") / "data"
    res = run_python(["-m", "fmbrdf_mi", "example-data", str(out)], cwd=out.parent, timeout=600)
    assert res.returncode == 0, f"fmbrdf-mi example-data failed:\n{res.stdout[-3000:]}\n{res.stderr[-6000:]}"
    return out


def _copy_or_link(src, dst):
    """Large example files (the MERL tables) hard-linked, the rest copied."""
    if os.path.getsize(src) > 1 << 20:
        try:
            os.link(src, dst)
            return dst
        except OSError:
            pass
    return shutil.copy2(src, dst)


def test_example_data(example_data):
    """The example data holds every file its module lists; the captures show the sphere where the mask
    says (the sum of each 2 x 2 super-pixel's raw samples), the angle images are the mosaic's pixels of
    each polariser angle (IMX250MZR: 90 45 / 135 0), the MERL files are full-size; and the command
    refuses a directory that exists in one line, exit status 1, writing nothing."""
    import numpy as np
    from PIL import Image
    from fmbrdf_mi.brdf_fit import merl
    from fmbrdf_mi.synthetic import examples

    names = set(re.findall(r"``([\w./]+\.(?:png|npy|tif|toml|json|binary|csv|txt))``", examples.__doc__))
    names |= {f"i{a}.tif" for a in (0, 45, 90, 135)}
    assert len(names) > 20
    missing = sorted(n for n in names if "..." not in n and not (example_data / n).exists())
    assert not missing, missing
    assert (example_data / "data" / "blob" / "calibration" / "L.txt").exists()
    for raw_name, mask_name, block in (("capture.png", "mask.png", 2), ("a.png", "mask.png", 2),
                                       ("colour_raw.png", "colour_mask.png", 4)):
        raw = np.asarray(Image.open(example_data / raw_name), dtype=float)
        mask = np.asarray(Image.open(example_data / mask_name)) > 0
        h, w = mask.shape
        assert raw.shape == (block * h, block * w), (raw_name, raw.shape, mask.shape)
        cells = raw.reshape(h, block, w, block).mean(axis=(1, 3))
        assert cells[mask].mean() > 10 * max(cells[~mask].mean(), 1e-3), raw_name   # edge cells: partly on it
        assert (cells[mask] > 0).mean() > 0.9, raw_name
    raw = np.asarray(Image.open(example_data / "capture.png"))
    for angle, (r, c) in {90: (0, 0), 45: (0, 1), 135: (1, 0), 0: (1, 1)}.items():
        assert np.array_equal(np.asarray(Image.open(example_data / f"i{angle}.tif")), raw[r::2, c::2]), angle
    assert np.array_equal(np.load(example_data / "raw.npy"), raw)
    for name in ("glossy", "matte"):
        path = example_data / "merl" / f"{name}.binary"
        assert os.path.getsize(path) == 12 + 8 * 3 * 90 * 90 * 180
        assert np.isfinite(merl.read_merl(path)).mean() > 0.4
    listing = sorted(p.relative_to(example_data) for p in example_data.rglob("*"))
    res = run_python(["-m", "fmbrdf_mi", "example-data", str(example_data)], cwd=example_data.parent)
    assert res.returncode == 1 and len(res.stderr.strip().splitlines()) == 1 and "exists" in res.stderr, res.stderr
    assert sorted(p.relative_to(example_data) for p in example_data.rglob("*")) == listing
    assert not list(example_data.parent.glob(".*.part"))


def test_the_docs_have_shell_blocks():
    """The shell runner finds the how-tos' commands (a wrong fence pattern would make every page pass)."""
    names = {p.relative_to(ROOT).as_posix() for p in SHELL_PAGES}
    assert {"README.md", "docs/getting-started.md", "docs/howto/render.md", "docs/howto/fit.md",
            "docs/howto/fit-joint.md", "docs/howto/fit-brdf.md", "docs/howto/dataset.md"} <= names
    assert shell_blocks(ROOT / "docs" / "howto" / "render.md")[0][1].startswith("fmbrdf-mi render")


@pytest.mark.parametrize("page", SHELL_PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_page_shell_blocks_run(page, tmp_path, example_data):
    rel = page.relative_to(ROOT).as_posix()
    if rel not in QUICK_SHELL_PAGES and not SLOW:
        pytest.skip(f"the commands of {rel} take minutes: FMBRDF_DOCS_SLOW=1 runs them")
    blocks = [(line, code) for line, code, marker in shell_blocks(page)
              if not (marker == "skip" or (marker == "slow" and not SLOW))]
    if not blocks:
        pytest.skip(f"every shell block of {rel} is marked skip (or slow)")
    before = repo_state()
    work = tmp_path / "work"
    shutil.copytree(example_data, work, copy_function=_copy_or_link)
    for name in ("scenes", "tools"):
        shutil.copytree(ROOT / name, work / name, ignore=shutil.ignore_patterns("__pycache__"))
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name, cmd in (("fmbrdf-mi", f'"{sys.executable}" -m fmbrdf_mi'), ("python", f'"{sys.executable}"')):
        (bin_dir / name).write_text(f'#!/bin/sh\nexec {cmd} "$@"\n')
        (bin_dir / name).chmod(0o755)
    env = _env()
    env["PATH"] = os.pathsep.join([str(bin_dir), env.get("PATH", "")])
    for line, code in blocks:
        t0 = time.perf_counter()
        try:
            res = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", code], cwd=work, env=env,
                                 capture_output=True, text=True, timeout=SHELL_BLOCK_TIMEOUT)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the shell block of {rel} at line {line} ran past {SHELL_BLOCK_TIMEOUT} s")
        assert res.returncode == 0, (f"the shell block of {rel} at line {line} failed (exit {res.returncode}):\n"
                                     f"{res.stdout[-3000:]}\n{res.stderr[-6000:]}")
        print(f"{rel}:{line}: {time.perf_counter() - t0:.1f} s")
    assert repo_state() == before, f"the shell blocks of {rel} changed the repository's files"


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
