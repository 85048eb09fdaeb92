"""The documentation: the site builds in strict mode (a broken reference, a missing page or a
docstring mkdocstrings cannot parse fails), the README's links resolve, and the results pages
are the output of the commands that measure them."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_site_builds_in_strict_mode(tmp_path):
    pytest.importorskip("mkdocs", reason="mkdocs is not installed: pip install -e '.[docs]'")
    pytest.importorskip("mkdocstrings", reason="mkdocstrings is not installed: "
                                               "pip install -e '.[docs]'")
    site = tmp_path / "site"
    # no -q: mkdocs -q hides the warnings that --strict turns into a failure
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                           "-f", str(ROOT / "mkdocs.yml"), "-d", str(site)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300,
                          env={**__import__("os").environ, "NO_MKDOCS_2_WARNING": "1"})
    assert proc.returncode == 0, proc.stdout + proc.stderr
    for page in ("index.html", "getting-started.html", "api/stages.html",
                 "reference/cli.html", "results/paper.html"):
        assert (site / page).is_file(), page
    # the API pages are generated from the docstrings, the CLI page from the parser
    api = (site / "api" / "stages.html").read_text(encoding="utf-8")
    assert "Pipeline" in api and "fit" in api
    cli = (site / "reference" / "cli.html").read_text(encoding="utf-8")
    assert "hsiffc correct" in cli and "--overwrite" in cli
    # equations are typeset when the site is built (no raw TeX, nothing loaded from a CDN)
    physics = (site / "physics.html").read_text(encoding="utf-8")
    assert physics.count('class="hsiffc-math"') >= 7 and "\\tag{" not in physics
    for page in site.rglob("*.html"):
        text = page.read_text(encoding="utf-8")
        assert not re.search(r'<script[^>]+src="https?://|<link[^>]+href="https?://', text), \
            f"{page.relative_to(site)} loads a script, font or style from the network"
    _links_work_from_disk(site)


def _links_work_from_disk(site: Path) -> None:
    """Every link of every page, followed as a browser does with file:// URLs, reaches a
    file: no link to a folder (a folder listing from disk), none to a missing page."""
    broken = []
    pages = [p for p in site.rglob("*.html") if p.name != "404.html"]
    for page in pages:
        text = page.read_text(encoding="utf-8")
        for href in re.findall(r'<a[^>]+href="([^"#?]*)[^"]*"', text):
            if not href or re.match(r"[a-z]+:", href):
                continue  # an anchor on the page itself, or another site (mailto:, https:)
            target = (page.parent / href).resolve()
            if href.endswith("/") or target.is_dir() or not target.is_file():
                broken.append(f"{page.relative_to(site)} -> {href}")
    assert len(pages) > 20 and not broken, broken[:20]


def test_readme_links_resolve():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [link for link in links if not re.match(r"[a-z]+://", link)]
    assert local, "the README links into the docs"
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_readme_is_short_and_opens_with_the_two_commands():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 220
    blocks = re.findall(r"```bash\n(.*?)\n```", "\n".join(lines[:12]), re.S)
    assert len(blocks) == 2, "the README opens with two set-up commands"
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert blocks[1].strip() in ci, "the README's test command is what .ci/run runs"


def _results_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("docs_results", ROOT / "docs" / "gen" /
                                                  "results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_results_pages_are_what_their_commands_produced():
    """Each results page is rendered from the stored outputs of its command; a page edited by
    hand (or outputs changed without re-rendering) fails here."""
    gen = _results_module()
    for name in gen.PAGES:
        page = ROOT / "docs" / "results" / f"{name}.md"
        assert page.is_file(), f"missing {page}: run python3 docs/gen/results.py {name}"
        assert page.read_text(encoding="utf-8") == gen.render(name), \
            f"{page} differs from its command's outputs: rerun python3 docs/gen/results.py {name}"
        run_json = ROOT / "docs" / "results" / name / "run.json"
        if not run_json.is_file():
            # only a page allowed to wait for its measurement, and it then says so
            assert name in gen.UNMEASURED_OK, f"{name}: no outputs in docs/results/{name}/"
            assert "Not measured yet" in page.read_text(encoding="utf-8")
            continue
        run = __import__("json").loads(run_json.read_text(encoding="utf-8"))
        assert run["command"] and run["git_commit"]
        assert str(ROOT.parent) + "/" not in page.read_text(encoding="utf-8"), \
            f"{page} quotes an absolute path of the machine that measured it"


def test_readme_speed_table_follows_the_benchmark_json(tmp_path, monkeypatch):
    """The README's speed rows are read from the structure benchmarks/run.py writes
    ({"machine", "runs": {bench: {"figures": [...]}}}): value, baseline, ratio, target, met."""
    gen = _results_module()
    fig = {"name": "closed-form response", "value": 250.0, "unit": "Mpx/s", "baseline": 50.0,
           "baseline_name": "numpy", "ratio": 5.0, "target": ">= 200 Mpx/s", "met": False,
           "note": ""}
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "benchmarks.json").write_text(__import__("json").dumps(
        {"machine": {"cores": 2, "machine": "x86_64"},
         "runs": {"bench_foundation": {"figures": [fig, {**fig, "target": ""}]},
                  "bench_read": {"hsiffc_stream_8bit_mb_s": 1.0}}}), encoding="utf-8")
    monkeypatch.setattr(gen, "RESULTS", tmp_path)
    rows = gen._speed_rows()
    assert rows == [("foundation", "closed-form response", "250 Mpx/s", "50 Mpx/s (numpy)",
                     "5 x", ">= 200 Mpx/s", "**not met**")]
    block = gen.readme_block()
    assert "| foundation | closed-form response | 250 Mpx/s |" in block
    assert "not measured yet" not in block
    # a target not met points to the page's section whose notes say where the time goes
    assert "time goes for each target not met" in block
    assert "[foundation](docs/results/benchmarks.md#foundation)" in block
    fig["met"] = True
    (tmp_path / "benchmarks" / "benchmarks.json").write_text(__import__("json").dumps(
        {"machine": {"cores": 2, "machine": "x86_64"},
         "runs": {"bench_foundation": {"figures": [fig]}}}), encoding="utf-8")
    assert "target not met" not in gen.readme_block()


def test_readme_results_table_is_generated():
    """The README's headline table is rendered from the results pages' stored outputs."""
    gen = _results_module()
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    i, j = text.index(gen.BEGIN), text.index(gen.END) + len(gen.END)
    assert text[i:j] == gen.readme_block(), \
        "README results table is stale or edited: run python3 docs/gen/results.py --render-only all"


def test_readme_pipeline_example_runs(tmp_path, monkeypatch):
    """The README's Python example runs as written, twice (its file is its own: no other
    snippet of the docs writes it), in a working directory with the sample cubes."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    code = re.findall(r"```python\n(.*?)```", text, re.S)[0]
    saved = re.findall(r'pipe\.save\("([^"]+)"', code)
    assert len(saved) == 1, "the README's pipeline example saves one file"
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sample_cubes").symlink_to(ROOT / "sample_cubes")
    for _ in range(2):
        scope = {}
        exec(compile(code, "README.md", "exec"), scope)  # noqa: S102 (our own README)
    cube = scope["cube"]
    assert cube.data.shape == (96, 128, 8) and cube.dq.shape == cube.data.shape
    assert (tmp_path / saved[0]).is_file()
    # no snippet or command elsewhere in the docs writes the same file name
    for page in [*(ROOT / "docs").rglob("*.md"), ROOT / "examples" / "pipeline.toml"]:
        body = page.read_text(encoding="utf-8")
        assert f"-o {saved[0]}" not in body and f'save("{saved[0]}"' not in body, page


def test_api_pages_document_public_modules_only():
    # the API reference names public modules and objects: no part of the path private (a
    # leading underscore) and no old path kept only for compatibility (hsiffc/_moved.py); the
    # strict build above fails on a name that does not exist
    from hsiffc._moved import MOVED

    names = [m.group(1) for page in sorted((ROOT / "docs" / "api").glob("*.md"))
             for m in re.finditer(r"^:::\s+(\S+)", page.read_text(), re.M)]
    assert names, "the API pages document nothing"
    private = [n for n in names if any(part.startswith("_") for part in n.split("."))]
    assert private == [], f"private modules on the API pages: {private}"
    moved = [n for n in names if any(n == old or n.startswith(old + ".") for old in MOVED)]
    assert moved == [], f"old paths on the API pages (use the new ones): {moved}"
