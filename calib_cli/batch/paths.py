"""Inputs and output paths.

Each input (a file, or every file under a directory that matches the
pipeline's globs) gets a key: its path relative to the directory given (a
file given by itself: relative to the working directory when below it, else
its name), made safe. Its outputs go to OUT/<key>/<step output>. Keys are
deterministic and can never leave OUT: every component is reduced to
[A-Za-z0-9._-], may not start with a dot, "." and ".." cannot survive, and
the final path is checked to resolve inside OUT. Where making a name safe
changed it, or two inputs would share a key, a short hash of the original
relative path is appended, so distinct inputs never share outputs.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from calib_cli.errors import InputError

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]")
MAX_COMPONENT = 100


@dataclass(frozen=True)
class BatchInput:
    path: str  # as found on disk
    rel: str  # relative name used for the key (posix)
    key: str  # output sub-directory, safe


def _short(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8", "surrogateescape")).hexdigest()[:8]


def safe_component(c: str) -> str:
    s = _UNSAFE.sub("_", c).lstrip(".-") or "_"
    return s[:MAX_COMPONENT]


def output_key(rel: str) -> str:
    """A safe relative directory for ``rel`` (see module doc)."""
    parts = [p for p in PurePosixPath(rel.replace("\\", "/")).parts if p not in ("/", "")]
    name = parts[-1] if parts else "_"
    stem, dot, ext = name.rpartition(".")
    # "rec.csv" -> "rec-csv": a CSV and a raw.h5 of the same stem stay apart
    leaf = f"{stem}-{ext}" if dot and stem else name
    comps = [safe_component(p) for p in parts[:-1]] + [safe_component(leaf)]
    key = "/".join(comps)
    if key != "/".join(parts[:-1] + [leaf]):
        key += f"-{_short(rel)}"
    return key


def discover(inputs, globs, exclude: str | None = None) -> list[BatchInput]:
    """Expand directories (sorted, hidden files and the output dir skipped)
    and give every input its key. Missing inputs are kept: they fail alone."""
    found: list[tuple[str, str]] = []
    excl = Path(exclude).resolve() if exclude else None
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            matches = set()
            for g in globs:
                for m in p.glob(g):
                    if not m.is_file():
                        continue
                    rel = m.relative_to(p)
                    if any(part.startswith(".") for part in rel.parts):
                        continue
                    if excl is not None and m.resolve().is_relative_to(excl):
                        continue
                    matches.add(rel.as_posix())
            found += [(str(p / r), r) for r in sorted(matches)]
        else:  # a file: its path below the working directory, else its name
            try:
                rel = p.resolve().relative_to(Path.cwd().resolve()).as_posix()
            except ValueError:
                rel = p.name
            found.append((str(p), rel))
    out, seen = [], {}
    for path, rel in found:
        key = output_key(rel)
        if key in seen and seen[key] != path:
            key = f"{key}-{_short(str(Path(path).resolve()))}"
        seen.setdefault(key, path)
        out.append(BatchInput(path, rel, key))
    # the same file named twice is processed once
    uniq, done = [], set()
    for b in out:
        if b.key not in done:
            done.add(b.key)
            uniq.append(b)
    return uniq


def inside(out_dir: str, key: str, name: str) -> str:
    """OUT/key/name, refusing anything that would resolve outside OUT."""
    root = Path(out_dir).resolve()
    target = (root / key / name).resolve()
    if not target.is_relative_to(root) or target == root:
        raise InputError(f"output path {key}/{name} would leave the output directory", out_dir)
    return str(target)


def vanished(inputs, out_dir: str, found: list[BatchInput]) -> list[BatchInput]:
    """Inputs of an earlier run under a directory given now that are gone
    (deleted or moved): found through the ``batch_input``/``batch_key``
    attributes of the outputs under OUT. They are run like a missing file
    (they fail, "no such file"; their old outputs are left alone), so a
    deleted recording never passes silently (issue 15)."""
    import os

    dirs = [Path(i).resolve() for i in inputs if Path(i).is_dir()]
    root = Path(out_dir)
    if not dirs or not root.is_dir():
        return []
    known = {b.key for b in found}
    out, seen = [], set()
    for base, subdirs, files in os.walk(root):
        subdirs[:] = [d for d in subdirs if not d.startswith(".")]
        if Path(base).relative_to(root).as_posix() in known:
            continue  # an input found now: its outputs are not opened (large archives)
        for f in sorted(files):
            if not f.endswith(".h5") or f.startswith("."):
                continue
            src, key = _attrs(os.path.join(base, f), ("batch_input", "batch_key"))
            if not src or not key or key in known or key in seen:
                continue
            sp = Path(src)
            try:
                full = sp.resolve()
            except (OSError, RuntimeError):
                continue
            hit = next((d for d in dirs if full.is_relative_to(d)), None)
            if hit is None or sp.exists():
                continue
            seen.add(key)
            out.append(BatchInput(str(src), full.relative_to(hit).as_posix(), key))
    return sorted(out, key=lambda b: b.key)


def _attrs(path: str, names) -> list:
    """String root attributes of one of batch's own outputs ('' when absent or unreadable)."""
    try:
        import h5py

        with h5py.File(path, "r") as h5:
            vals = [h5.attrs.get(n, "") for n in names]
    except Exception:  # noqa: BLE001 - not ours or damaged: not an input of ours
        return ["" for _ in names]
    return [v.decode(errors="replace") if isinstance(v, bytes) else str(v) for v in vals]
