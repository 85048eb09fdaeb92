"""A new user's first ten minutes: the README's two commands, the demo run again, what a
first run says while it compiles, and the working directory the tests leave alone."""

from __future__ import annotations

import io
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hsiffc.cli import main
from hsiffc.cli.status import COMPILE_NOTICE, CompileWatch, command_status

ROOT = Path(__file__).resolve().parents[2]
pytest_plugins = ["pytester"]


def readme_blocks() -> list[tuple[str, str]]:
    """The README's fenced code blocks right after its title, before any prose:
    (language, code) pairs."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    title, rest = text.split("\n", 1)
    assert title.startswith("# "), "the README starts with its title"
    fence = re.compile(r"\s*```(\w*)\n(.*?)\n```", re.S)
    blocks, pos = [], 0
    while (m := fence.match(rest, pos)):
        blocks.append(m.groups())
        pos = m.end()
    return blocks


def ci_command() -> str:
    """The line of ``.ci/run`` that installs and runs the tests."""
    lines = [ln for ln in (ROOT / ".ci" / "run").read_text().splitlines()
             if "pytest" in ln and not ln.lstrip().startswith("#")]
    assert len(lines) == 1, f".ci/run runs one test command, found {lines}"
    return lines[0].strip()


def test_readme_opens_with_two_bash_blocks_and_the_second_is_what_ci_runs():
    blocks = readme_blocks()
    assert [lang for lang, _ in blocks] == ["bash", "bash"], blocks
    install_and_demo, tests = (code.strip() for _, code in blocks)
    assert "\n" not in install_and_demo and "\n" not in tests
    assert install_and_demo.startswith("python3 -m pip install -e . && ")
    assert "demo sample_cubes" in install_and_demo
    assert tests == ci_command()


def test_ci_checks_the_tests_leave_the_working_tree_clean():
    script = (ROOT / ".ci" / "run").read_text()
    assert "git status --porcelain" in script
    # the check comes after the test command, and fails the run
    assert script.index(ci_command()) < script.rindex("git status --porcelain")
    assert "exit 1" in script.split(ci_command(), 1)[1]


def test_demo_runs_again_into_its_own_folder(demo_result, sample_cubes, tmp_path, monkeypatch,
                                             capsys):
    import hsiffc.reports.demo as demo

    monkeypatch.setattr(demo, "compute_demo", lambda samples: demo_result)
    monkeypatch.chdir(tmp_path)
    assert main(["demo", str(sample_cubes)]) == 0
    folder = tmp_path / "hsiffc-demo"
    assert demo.is_demo_folder(folder)
    (folder / "my_notes.txt").write_text("mine")
    first = {name: (folder / name).stat().st_mtime_ns for name in demo.DEMO_FILES}
    assert main(["demo", str(sample_cubes)]) == 0, capsys.readouterr().err
    assert all((folder / name).stat().st_mtime_ns >= first[name] for name in first)
    assert (folder / "my_notes.txt").read_text() == "mine"  # only the demo's files replaced
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hsiffc-demo"]


def test_demo_refuses_a_folder_it_did_not_write(demo_result, sample_cubes, tmp_path,
                                                monkeypatch, capsys):
    import hsiffc.reports.demo as demo

    monkeypatch.setattr(demo, "compute_demo", lambda samples: demo_result)
    other = tmp_path / "results"
    other.mkdir()
    (other / "pipeline.npz").write_bytes(b"someone else's")
    assert main(["demo", str(sample_cubes), "-o", str(other)]) == 2
    err = capsys.readouterr().err
    assert "results: already holds files (pipeline.npz)" in err and "--overwrite" in err
    assert (other / "pipeline.npz").read_bytes() == b"someone else's"
    # a link named like one of the demo's files in its own folder is not written through
    own = tmp_path / "own"
    assert main(["demo", str(sample_cubes), "-o", str(own)]) == 0
    (own / "pipeline.npz").unlink()
    (own / "pipeline.npz").symlink_to(other / "pipeline.npz")
    assert main(["demo", str(sample_cubes), "-o", str(own)]) == 2
    assert "is a symbolic link" in capsys.readouterr().err
    assert (other / "pipeline.npz").read_bytes() == b"someone else's"


def _compile_fresh(module: str):
    """Compile a new tiny function attributed to ``module`` (never cached)."""
    from numba import njit

    def add_one(x):
        return x + 1
    add_one.__module__ = module
    return njit(add_one)(1)


def test_compile_watch_counts_hsiffc_functions_only():
    from numba.core import event

    changes = []
    watch = CompileWatch(lambda: changes.append(1))
    with event.install_listener("numba:compile", watch):
        _compile_fresh("somebody_else")
        assert watch.started == 0
        _compile_fresh("hsiffc.kernels.example")
    assert watch.started == watch.finished == 1 and not watch.compiling and changes


def test_first_compile_is_announced_off_a_terminal():
    out = io.StringIO()
    with command_status("demo", stream=out) as watch:
        _compile_fresh("hsiffc.kernels.example")
        _compile_fresh("hsiffc.kernels.example")
    text = out.getvalue().splitlines()
    assert watch.finished == 2
    assert text[0] == f"hsiffc demo: {COMPILE_NOTICE}"  # once, at the first compilation
    assert text[1].startswith("hsiffc demo: compiled 2 kernel functions in ") and len(text) == 2
    quiet = io.StringIO()
    with command_status("demo", stream=quiet):
        pass  # nothing compiled: nothing said
    assert quiet.getvalue() == ""


def test_status_line_on_a_terminal_shows_the_latest_library_message():
    import logging

    out = io.StringIO()
    with command_status("demo", stream=out, terminal=True) as watch:
        logging.getLogger("hsiffc.example").info("fitting the leakage model")
        _compile_fresh("hsiffc.kernels.example")
        import time
        time.sleep(0.3)  # a few redraws (8 per second)
    text = out.getvalue()
    assert COMPILE_NOTICE in text and watch.finished == 1
    assert "compiled 1 kernel functions" in text
    # the library's INFO record fed the line but was not printed as a log line
    assert "INFO" not in text


def _run(cmd: str, cwd: Path, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=1800)


@pytest.mark.slow
def test_readme_blocks_pass_on_a_fresh_clone_twice(tmp_path):
    """The README's first block twice, then the second block's collection, in a fresh clone
    of this repository, run verbatim by bash with a virtual environment's ``python3`` first
    on PATH. The environment sees this machine's packages (``--system-site-packages``) and
    pip's environment says ``--no-deps`` (they are installed already), so pip installs the
    clone itself, editable; pip still builds it in isolation as a user's pip does, which
    fetches the build requirements (setuptools, wheel) from the package index: without one
    the test skips. Compiling the kernels in the clone makes it slow (minutes on 2 cores)."""
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs git and this repository's .git to clone it")
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)],
                   check=True)
    env = {**os.environ, "PATH": f"{venv / 'bin'}{os.pathsep}{os.environ['PATH']}",
           "PIP_NO_DEPS": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1",
           "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    env.pop("HSIFFC_SHARED_DATA", None)
    env.pop("PYTHONPATH", None)
    (block1, _), (block2, _) = ((code.strip(), lang) for lang, code in readme_blocks())
    said = []
    for attempt in (1, 2):
        res = _run(block1, clone, env)
        if res.returncode and re.search(r"No matching distribution|Could not find a version|"
                                        r"Failed to establish a new connection", res.stderr):
            pytest.skip("pip cannot reach a package index for the build requirements")
        assert res.returncode == 0, f"README block 1, run {attempt}:\n{res.stderr[-3000:]}"
        assert "level off below full scale" in res.stdout
        said.append(COMPILE_NOTICE in res.stderr)
    assert said == [True, False], "the first run says it compiles, the second has nothing to"
    res = _run(block2, clone, {**env, "PYTEST_ADDOPTS": "--collect-only -q -p no:cacheprovider"})
    assert res.returncode == 0, f"README block 2 (collection):\n{res.stdout[-3000:]}"
    assert re.search(r"\d+ tests? collected|\d+/\d+ tests collected", res.stdout), \
        res.stdout[-2000:]
    status = subprocess.run(["git", "status", "--porcelain"], cwd=clone, capture_output=True,
                            text=True, check=True).stdout
    assert status == "", f"the README's commands left files in the clone:\n{status}"


def test_a_test_that_writes_the_working_directory_fails(pytester):
    pytester.makeconftest((ROOT / "tests" / "conftest.py").read_text(encoding="utf-8"))
    pytester.makepyfile(test_stray="""
        from pathlib import Path

        def test_writes_here():
            Path("stray.txt").write_text("x")

        def test_writes_in_tmp_path(tmp_path, monkeypatch):
            monkeypatch.chdir(tmp_path)
            Path("fine.txt").write_text("x")
        """)
    res = pytester.runpytest_inprocess("-p", "no:cacheprovider", "-o", "addopts=")
    res.assert_outcomes(passed=2, errors=1)
    res.stdout.fnmatch_lines(["*test_writes_here touched the current directory*created "
                              "stray.txt*tmp_path*"])


def test_getting_started_opens_with_the_readme_commands_and_types_no_counts():
    page = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```bash\n(.*?)\n```", page, re.S)
    assert [b.strip() for b in blocks[:2]] == [code.strip() for _, code in readme_blocks()]
    # a count pytest prints is not typed into the page (it drifts: "4 deselected" was 7)
    assert not re.search(r"\d+ deselected|(?:One|Two|Three|Four|Five|Six|Seven) test",
                         page), "say what pytest's line counts, not the number"


def _subcommands():
    import argparse

    from hsiffc.cli import build_parser

    def walk(parser, prefix):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, child in action.choices.items():
                    nested = [a for a in child._actions
                              if isinstance(a, argparse._SubParsersAction)]
                    if nested:
                        yield from walk(child, f"{prefix}{name} ")
                    else:
                        yield f"{prefix}{name}", child
    return list(walk(build_parser(), ""))


def test_every_command_help_ends_with_examples_that_parse():
    import shlex

    from hsiffc.cli import build_parser

    commands = _subcommands()
    assert len(commands) >= 15
    for name, parser in commands:
        text = parser.format_help().rstrip()
        assert "\nexamples:\n" in text, f"hsiffc {name} --help has no examples"
        examples = text.split("\nexamples:\n", 1)[1].splitlines()
        assert 1 <= len(examples) <= 2, name
        for line in examples:
            argv = shlex.split(line.strip())
            assert argv[0] == "hsiffc" and " ".join(argv[1:]).startswith(name), line
            try:
                build_parser().parse_args(argv[1:])  # options and values as the parser takes
            except SystemExit as exc:
                pytest.fail(f"the example {line.strip()!r} of hsiffc {name} does not parse "
                            f"(exit {exc.code})")


def test_stages_summaries_are_whole_sentences(capsys):
    assert main(["stages"]) == 0
    out = capsys.readouterr().out.splitlines()
    summaries = [line.strip() for line in out if line.startswith(" ")]
    assert summaries and all(s.endswith((".", "!", "?")) for s in summaries), summaries
    assert not any("``" in s or ":func:" in s for s in summaries)


def test_uniformity_prints_its_table_without_json(sample_cubes, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["uniformity", str(sample_cubes / "test_2200K.tif")]) == 0
    out = capsys.readouterr().out
    assert "fixed-pattern non-uniformity" in out and "--json FILE" in out
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_info_describes_hsiffc_corrected_outputs(demo_result, sample_cubes, tmp_path, capsys):
    from hsiffc.batch import correct_batch

    cal = demo_result.calibration.save(tmp_path / "cal.npz")
    correct_batch([sample_cubes / "test_2200K.tif"], tmp_path / "out", cal)
    out_file = tmp_path / "out" / "test_2200K.corrected.tif"
    assert main(["info", str(out_file), "--json", str(tmp_path / "info.json")]) == 0
    out = capsys.readouterr().out
    assert "output of hsiffc correct" in out and "6 frames of 96 x 128 px" in out
    assert demo_result.calibration.identity in out and "exposures 16.125, 32.25 ms" in out
    import json

    doc = json.loads((tmp_path / "info.json").read_text())
    assert doc["n_frames"] == 6 and doc["calibration"]["identity"] == demo_result.calibration.identity


def test_make_samples_points_to_pages_that_exist():
    text = (ROOT / "sample_cubes" / "make_samples.py").read_text(encoding="utf-8")
    refs = re.findall(r"docs/[\w/.-]+\.md", text)
    assert refs and all((ROOT / r).is_file() for r in refs), refs
    assert '"Data format"' not in text  # the README section it named is long gone


def test_calibrate_reports_its_progress_to_the_status_line(sample_cubes, tmp_path, caplog):
    import logging

    caplog.set_level(logging.INFO, logger="hsiffc")
    assert main(["calibrate", str(sample_cubes / "sweep_2900K.tif"), "-o",
                 str(tmp_path / "cal.npz")]) == 0
    rows = [r.getMessage() for r in caplog.records if "rows fitted" in r.getMessage()]
    assert rows and rows[-1] == "calibrating: 96 of 96 rows fitted (100 %)"
