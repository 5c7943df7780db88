"""`pip install .` ships the docs the help texts name: every "docs/NAME.md" in a
help text exists, is covered by pyproject's data-files (share/calib/docs), and
a wheel built from the tree holds it; `calib --help` says where docs/ is."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import click
import pytest

ROOT = Path(__file__).resolve().parent.parent
DOC_REF = re.compile(r"docs/[A-Za-z0-9_.-]+\.md")


def _help_refs() -> set[str]:
    from calib_cli.cli import main

    main.register_all()
    refs = set()

    def walk(cmd, ctx):
        text = (cmd.help or "") + " ".join(getattr(p, "help", None) or "" for p in cmd.params)
        refs.update(DOC_REF.findall(text))
        if isinstance(cmd, click.Group):
            for n in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, n)
                walk(sub, click.Context(sub, parent=ctx, info_name=n))

    walk(main.cli, click.Context(main.cli, info_name="calib"))
    return refs


def _data_files() -> dict[str, str]:
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    dest_of = {}
    for dest, patterns in cfg["tool"]["setuptools"]["data-files"].items():
        for pat in patterns:
            for f in ROOT.glob(pat):
                dest_of[f.relative_to(ROOT).as_posix()] = dest
    return dest_of


def test_every_doc_a_help_text_names_is_shipped():
    refs = _help_refs()
    assert "docs/commands.md" in refs and len(refs) > 10
    dest_of = _data_files()
    for ref in sorted(refs):
        assert (ROOT / ref).is_file(), f"a help text names {ref}, which does not exist"
        assert dest_of.get(ref) == "share/calib/docs", f"{ref} is not in the wheel's data-files"
    for f in (ROOT / "docs").rglob("*"):  # and the files the docs link to
        if f.is_file():
            rel = f.relative_to(ROOT).as_posix()
            assert dest_of.get(rel) == "share/calib/" + f.parent.relative_to(ROOT).as_posix(), rel


def test_help_says_where_the_docs_are():
    from calib_cli.docs_path import docs_dir

    r = subprocess.run([sys.executable, "-m", "calib_cli", "--help"], capture_output=True,
                       text=True, timeout=60, cwd=ROOT)
    assert (docs_dir() / "commands.md").is_file()
    assert f"docs/ (named in the help texts): {docs_dir()}" in " ".join(r.stdout.split())


def test_wheel_holds_the_docs(tmp_path):
    src = tmp_path / "src"
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if files.returncode != 0:
        pytest.skip("not a git checkout")
    for rel in files.stdout.split("\n"):
        if rel and rel.split("/")[0] in ("pyproject.toml", "README.md", "calib_cli", "docs",
                                         "profiles") and (ROOT / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / rel, src / rel)
    # as `pip install .` builds it: an isolated build with pyproject's build requirements
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                        str(tmp_path / "dist"), str(src)],
                       capture_output=True, text=True, timeout=600)
    if r.returncode != 0 and re.search(r"No matching distribution|Could not find a version|"
                                       r"Network is unreachable|Failed to establish", r.stderr):
        pytest.skip("the build requirements (setuptools>=77) are not reachable here")
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = (tmp_path / "dist").glob("*.whl")
    names = set(zipfile.ZipFile(whl).namelist())
    data = next(n.split("/")[0] for n in names if ".data/" in n)
    for ref in sorted(_help_refs()):
        assert f"{data}/data/share/calib/{ref}" in names, ref
    assert "calib_cli/cli/_tree.py" in names and "calib_cli/docs_path.py" in names
