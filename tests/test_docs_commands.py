"""Every command and fit method has a section in docs/commands.md."""

from pathlib import Path

from calib_cli.cli.main import cli


def test_every_command_documented():
    text = (Path(__file__).resolve().parents[1] / "docs" / "commands.md").read_text()
    missing = [name for name in cli.commands if f"## calib {name}" not in text]
    fit = cli.commands["fit"]
    missing += [f"fit {m}" for m in fit.commands if f"## calib fit {m}" not in text]
    assert not missing, f"docs/commands.md lacks: {missing}"
