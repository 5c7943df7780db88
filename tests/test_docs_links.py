"""Docs stay true: docs/contract.md is the contract's text, every relative link
in README.md and docs/*.md resolves, and every option that docs/commands.md
gives under a `## calib ...` heading exists on that command in the click tree.
Each checker is also run on a planted mistake, so a checker that finds
nothing cannot pass silently."""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest

from calib_cli.cli.main import cli

REPO = Path(__file__).resolve().parents[1]

# ---------------------------------------------------------------------------
# checkers

_FENCE = re.compile(r"^```.*?^```", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def broken_links(md_path: Path) -> list[str]:
    """Relative link targets of a Markdown file that do not exist (code
    blocks and inline code are not links; URLs and pure anchors are skipped)."""
    text = _CODE.sub("", _FENCE.sub("", md_path.read_text(encoding="utf-8")))
    # indented code blocks (4 spaces after a blank line) are not links either
    text = re.sub(r"(?m)^(    |\t).*$", "", text)
    bad = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
            continue
        path = target.split("#", 1)[0]
        if path and not (md_path.parent / path).exists():
            bad.append(target)
    return bad


def _tree(group: click.Group, prefix=()):
    """(('fit', 'accel'), command) for every command in the click tree."""
    ctx = click.Context(group)
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        yield (*prefix, name), cmd
        if isinstance(cmd, click.Group):
            yield from _tree(cmd, (*prefix, name))


GLOBAL_OPTS = {"--help", "-h", "--version", "--debug", "--quiet", "-q"}
_OPT = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")


def option_mismatches(text: str, root: click.Group = cli) -> list[str]:
    """'calib X: --opt' for every option given under a '## calib X ...' heading
    (in the heading or the section's text) that command X does not have."""
    commands = {path: cmd for path, cmd in _tree(root)}
    bad = []
    for sec in re.split(r"(?m)^(?=## )", text):
        head, _, body = sec.partition("\n")
        m = re.match(r"## calib (.*)", head)
        if not m:
            continue
        words = m.group(1).split()
        path = ()
        for w in words:
            if (*path, w) in commands:
                path = (*path, w)
            else:
                break
        if not path:
            bad.append(f"{head}: no such command")
            continue
        cmd = commands[path]
        have = set(GLOBAL_OPTS)
        for p in cmd.params:
            have.update(o for o in (*p.opts, *p.secondary_opts) if o.startswith("--"))
        # an option the text attributes to another command (`calib import ... --x`)
        # is that command's business: drop those code spans
        own = re.sub(r"`calib (?!" + re.escape(" ".join(path)) + r"\b)[^`]*`", "", body)
        for opt in sorted(set(_OPT.findall(head + "\n" + own)) - have):
            bad.append(f"calib {' '.join(path)}: {opt}")
    return bad


# ---------------------------------------------------------------------------
# the repository's docs


def test_contract_text_matches_shared_contract():
    shared = REPO.parent / "shared" / "CONTRACT.md"
    if not shared.is_file():
        pytest.skip("no ../shared/CONTRACT.md beside the repository")
    assert (REPO / "docs" / "contract.md").read_text(encoding="utf-8") == \
        shared.read_text(encoding="utf-8"), "docs/contract.md differs from ../shared/CONTRACT.md"


def test_every_relative_link_resolves():
    files = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    bad = {str(f.relative_to(REPO)): b for f in files if (b := broken_links(f))}
    assert not bad, f"broken links: {bad}"


def test_link_checker_finds_a_planted_broken_link(tmp_path):
    (tmp_path / "there.md").write_text("x")
    md = tmp_path / "doc.md"
    md.write_text("See [there](there.md#a), [web](https://x.org), [a](#top),\n"
                  "`[not](a-link.md)` and [gone](missing.md).\n\n```\n[x](nope.md)\n```\n")
    assert broken_links(md) == ["missing.md"]


def test_commands_md_options_exist_in_the_cli():
    text = (REPO / "docs" / "commands.md").read_text(encoding="utf-8")
    assert not option_mismatches(text)


def test_option_checker_finds_a_planted_mismatch():
    text = ("# Commands\n\n## calib fit accel RAW --out CAL [--method auto] [--frobnicate]\n"
            "Text naming `--no-such-option`; `calib import csv --window 2` is import's.\n\n"
            "## calib show FILE [--json]\nFine.\n\n## calib nonesuch X\n")
    assert option_mismatches(text) == ["calib fit accel: --frobnicate",
                                       "calib fit accel: --no-such-option",
                                       "## calib nonesuch X: no such command"]
