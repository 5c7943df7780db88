"""Every runnable example of the user documentation runs (issue 35).

A runnable example is a fenced block opened with ```sh in README.md or
docs/*.md (synopses with placeholders are indented blocks and are not run).
Each page's blocks run in order, in one bash (-e: the first failing command
fails the test), in an empty directory where `sample_data`, `docs` and
`profiles` of the repository are at hand, with the `calib` of this
environment first on PATH: exactly what a user types from a checkout. A block
opened with ```sh slow (a fit of minutes) runs in `make validate
K=docs_examples` instead of `make test`.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FENCE = re.compile(r"^```sh( slow)?[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# the user pages of a task: each shows what to do with a runnable example
MUST_HAVE = ("README.md", "accel.md", "gyro.md", "align.md", "allan.md", "compare.md",
             "diagnose.md", "plan.md", "report.md", "rimu.md", "simulate.md", "thermal.md",
             "turntable.md")


def blocks(page: Path) -> list[tuple[bool, str]]:
    """[(slow, code)] of a page's runnable examples, in order."""
    return [(bool(m.group(1)), m.group(2)) for m in FENCE.finditer(page.read_text("utf-8"))]


def _run(page: Path, code: str, tmp: Path) -> None:
    for name in ("sample_data", "docs", "profiles"):
        if not (tmp / name).exists():
            (tmp / name).symlink_to(ROOT / name)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           "MPLBACKEND": "Agg", "COLUMNS": "120"}
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", code], cwd=tmp, env=env,
                       capture_output=True, text=True, timeout=3000)
    assert r.returncode == 0, (f"{page.name}: an example failed (exit {r.returncode}):\n{code}\n"
                               f"--- stderr:\n{r.stderr[-3000:]}")


def _pages(slow: bool) -> list:
    return [pytest.param(p, id=p.name) for p in PAGES
            if any(s == slow for s, _ in blocks(p))]


@pytest.mark.parametrize("page", _pages(False))
def test_the_examples_of_the_page_run(page, tmp_path):
    code = "\n".join(c for s, c in blocks(page) if not s)
    _run(page, code, tmp_path)


@pytest.mark.slow
@pytest.mark.part("docs_examples")
@pytest.mark.parametrize("page", _pages(True))
def test_the_slow_examples_of_the_page_run(page, tmp_path):
    code = "\n".join(c for _, c in blocks(page))  # the quick ones first: the slow may use them
    _run(page, code, tmp_path)


def test_every_task_page_has_a_runnable_example():
    missing = [n for n in MUST_HAVE
               if not blocks(ROOT / n if n == "README.md" else ROOT / "docs" / n)]
    assert not missing, f"pages without a ```sh example: {missing}"


def test_the_fence_finder():
    page = ROOT / "README.md"
    text = "x\n\n```sh\ncalib --help\n```\n\n    calib fit X\n\n```sh slow\ncalib a\n```\n"
    assert [(s, c) for s, c in FENCE.findall(text)] == [("", "calib --help\n"),
                                                        (" slow", "calib a\n")]
    assert page.exists()


@pytest.mark.slow
@pytest.mark.part("docs_examples")
def test_the_diagnose_walkthrough_quotes_the_current_figures(tmp_path):
    """docs/diagnose.md's walkthrough quotes the residuals and scores of its own run."""
    import json

    page = ROOT / "docs" / "diagnose.md"
    code = next(c for s, c in blocks(page) if s and "diagnose_turntable.toml" in c)
    _run(page, code, tmp_path)
    d = json.loads((tmp_path / "diag.json").read_text(encoding="utf-8"))
    text = page.read_text(encoding="utf-8")
    walk = text[text.index("## Walkthrough"):text.index("## Validation")]
    quoted = [f"{d['residual_rms_initial']:.2f}", f"{d['residual_rms_final']:.3f}",
              f"{d['noise_rms']:.3f}"]
    for st in d["steps"]:
        quoted += [f"{st['score']:.0f}", f"{st['threshold']:.1f}",
                   f"{st['residual_rms_before']:.2f} -> "]
    missing = [q for q in quoted if q not in walk]
    assert not missing, f"docs/diagnose.md's walkthrough is stale: {missing} not quoted"
    assert [st["with"] for st in d["steps"]] == ["lever_arm", "g_sensitivity"]
