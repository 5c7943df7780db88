"""Pipeline files (TOML): the steps of a batch and their options.

    name = "production-accel"
    glob = ["**/*.csv", "**/*.h5"]     # files taken from a directory input

    [[step]]
    step = "import"
    plan = "{dir}/plan.toml"           # placeholders: {dir} {stem} {name}

    [[step]]
    step = "fit"
    method = "accel"
    options = { method = "auto" }

    [[step]]
    step = "apply"

    [[step]]
    step = "export"

Nothing in it is evaluated: values are plain TOML data, and placeholders are
replaced textually (unknown placeholders are an error).
"""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path

from calib_cli import __version__
from calib_cli.batch.registry import StepDef, lookup
from calib_cli.errors import InputError

DEFAULT_GLOB = ("**/*.csv", "**/*.h5")
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")


@dataclass(frozen=True)
class PipelineStep:
    name: str
    method: str | None
    options: dict  # as written (file options unresolved)
    index: int
    output_name: str  # file name inside the input's output directory

    @property
    def label(self) -> str:
        return f"{self.name} {self.method}" if self.method else self.name

    def definition(self, path: str = "<pipeline>") -> StepDef:
        return lookup(self.name, self.method, f"step {self.index + 1}", path)

    def spec(self) -> dict:
        return {"step": self.name, "method": self.method, "options": self.options,
                "output": self.output_name}


@dataclass(frozen=True)
class Pipeline:
    name: str
    steps: tuple[PipelineStep, ...]
    globs: tuple[str, ...]
    base_dir: str  # relative file options are relative to the pipeline file
    path: str

    def sha256(self) -> str:
        """Hash of what the pipeline does (steps and options) and the tool version."""
        return digest({"tool_version": __version__,
                        "steps": [s.spec() for s in self.steps]})

    def to_dict(self) -> dict:
        """Plain data for workers (no objects cross process or network borders)."""
        return {"name": self.name, "globs": list(self.globs), "base_dir": self.base_dir,
                "path": self.path, "steps": [{"name": s.name, "method": s.method,
                                              "options": s.options, "index": s.index,
                                              "output_name": s.output_name}
                                             for s in self.steps]}

    @classmethod
    def from_dict(cls, d: dict) -> "Pipeline":
        return cls(d["name"], tuple(PipelineStep(**s) for s in d["steps"]), tuple(d["globs"]),
                   d["base_dir"], d["path"])


def digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"))
                          .encode()).hexdigest()


def fill_placeholders(value: str, source: str, where: str, path: str) -> str:
    """Replace {dir} {stem} {name} of the chain's input (text only)."""
    src = Path(source)
    table = {"dir": str(src.parent), "stem": src.stem, "name": src.name}

    def sub(m):
        key = m.group(1)
        if key not in table:
            raise InputError(f"{where}: unknown placeholder {{{key}}} in {value!r}; known: "
                             "{dir} {stem} {name}", path)
        return table[key]

    return _PLACEHOLDER.sub(sub, value)


def parse_pipeline(text: str, path: str = "<pipeline>") -> Pipeline:
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path) from None
    except RecursionError:
        raise InputError("not valid TOML: nested too deeply", path) from None
    from calib_cli.io.schema import strict_keys

    strict_keys(raw, {"name", "glob", "step", "description"}, path)
    globs = raw.get("glob", list(DEFAULT_GLOB))
    if isinstance(globs, str):
        globs = [globs]
    if not isinstance(globs, list) or not globs or not all(isinstance(g, str) and g
                                                           for g in globs):
        raise InputError("glob must be a pattern or a list of patterns", path)
    for g in globs:
        if Path(g).is_absolute() or ".." in Path(g).parts:
            raise InputError(f"glob {g!r} must stay inside the input directory", path)
    entries = raw.get("step")
    if not isinstance(entries, list) or not entries:
        raise InputError("pipeline has no [[step]] entries", path)
    steps, names = [], set()
    for i, e in enumerate(entries):
        where = f"step {i + 1}"
        if not isinstance(e, dict):
            raise InputError(f"{where} is not a table", path)
        name = e.get("step")
        if not isinstance(name, str) or not name:
            raise InputError(f"{where}: needs step = \"import\" | \"fit\" | \"apply\" | ...",
                             path)
        method = e.get("method")
        if method is not None and not isinstance(method, str):
            raise InputError(f"{where}: method must be a string", path)
        if not isinstance(e.get("options", {}), dict):
            raise InputError(f"{where}: options must be a table", path)
        opts = dict(e.get("options", {}))
        # options may also be written directly in the step table
        opts.update({k: v for k, v in e.items() if k not in ("step", "method", "options",
                                                             "output")})
        d = lookup(name, method if name == "fit" else None, where, path)
        if d.options is not None:
            bad = sorted(set(opts) - set(d.options))
            if bad:
                raise InputError(f"{where} ({d.label}): unknown option{'s' * (len(bad) > 1)} "
                                 f"{', '.join(bad)}; accepted: "
                                 f"{', '.join(d.options) or 'none'}", path)
        for fo in d.file_options:
            if fo not in opts and fo in d.optional_files:
                continue
            if fo not in opts or not isinstance(opts[fo], str):
                raise InputError(f"{where} ({d.label}): needs {fo} = \"FILE\"", path)
        out = e.get("output") or (f"cal-{method}" if name == "fit" else
                                  {"raw": "raw", "corrected": "corrected"}.get(d.makes, name))
        if not isinstance(out, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", out):
            raise InputError(f"{where}: output must be a plain file name, got {out!r}", path)
        out += d.suffix
        if out in names:  # the same step twice: number the files
            out = f"{Path(out).stem}-{i + 1}{d.suffix}"
        names.add(out)
        steps.append(PipelineStep(name, method if name == "fit" else None, opts, i, out))
    _check_chain(steps, path)
    base = str(Path(path).resolve().parent) if path != "<pipeline>" else str(Path.cwd())
    return Pipeline(str(raw.get("name", Path(path).stem)), tuple(steps), tuple(globs), base,
                    str(path))


def _check_chain(steps, path) -> None:
    """Every step's needs are made by an earlier step (or are the input)."""
    have = {"source", "raw"}  # a raw.h5 input is its own raw artifact
    for s in steps:
        d = s.definition(path)
        missing = [n for n in d.needs if n not in have]
        if missing:
            raise InputError(f"step {s.index + 1} ({d.label}) needs {', '.join(missing)}, "
                             "which no earlier step makes", path)
        have.add(d.makes)


def load_pipeline(path) -> Pipeline:
    p = str(path)
    try:
        text = Path(p).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", p) from None
    return parse_pipeline(text, p)
