"""Output path safety (issue 15): every file or directory a command writes.

- An output that resolves to an input of the same command (the same path, a
  symlink to it, a hard link: compared by ``st_dev``/``st_ino``) is a usage
  error (exit 2) raised before anything is written.
- An output that cannot be written (missing directory, no permission, a
  read-only or special file system such as /proc) is exit 2, one line.
- A directory where a file is expected is exit 3.
- Temporary files are named ``.NAME.calib-PID.tmp`` (directories
  ``.NAME.calib-PID.tmpdir``) beside the output; a later run writing the same
  output removes those whose process no longer runs (a killed run's leftovers).
- Written files follow the umask (``mkstemp`` alone would make them 0600).
- Two commands writing the same output at once: the second fails at once
  with exit 3 naming the holder (its process id and command line), through
  an flock on ``.NAME.calib-lock`` beside the output, held while writing and
  removed after (the kernel drops the lock of a killed run; its file is
  reused and removed by the next run). Never a mixed file either way: each
  run writes its own temp file and renames it whole.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
from pathlib import Path

from calib_cli.errors import InputError, OutputError

_TMP_RE = re.compile(r"^\.(?P<name>.+)\.calib-(?P<pid>\d+)(?:-\d+)?\.tmp(?:dir)?$")
# temp names of earlier calib versions: .NAME.XXXXXXXX.tmp (mkstemp) / .NAME.XXXXXXXX (mkdtemp)
_OLD_TMP_RE = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}(?:\.tmp)?$")
_OLD_TMP_AGE_S = 6 * 3600.0
_seq = 0


def current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def follow_umask(path, directory: bool = False) -> None:
    """Give ``path`` the mode a plain ``open()``/``mkdir()`` would have."""
    base = 0o777 if directory else 0o666
    with contextlib.suppress(OSError):
        os.chmod(path, base & ~current_umask())


def _same_file(a: os.stat_result, b: os.stat_result) -> bool:
    return a.st_dev == b.st_dev and a.st_ino == b.st_ino


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def clean_stale_temps(path) -> list[str]:
    """Remove the temp files/directories a killed run left beside ``path``."""
    import time

    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    removed = []
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return removed
    for e in entries:
        m = _TMP_RE.match(e.name)
        stale = False
        if m and m.group("name") == path.name:
            stale = not _pid_alive(int(m.group("pid")))
        else:
            m = _OLD_TMP_RE.match(e.name)
            if m and m.group("name") == path.name:
                with contextlib.suppress(OSError):
                    stale = time.time() - e.stat(follow_symlinks=False).st_mtime > _OLD_TMP_AGE_S
        if stale:
            with contextlib.suppress(OSError):
                if e.is_dir(follow_symlinks=False):
                    shutil.rmtree(e.path, ignore_errors=True)
                else:
                    os.unlink(e.path)
                removed.append(e.path)
    return removed


def temp_name(path, directory: bool = False) -> Path:
    global _seq
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    _seq += 1
    return parent / f".{path.name}.calib-{os.getpid()}-{_seq}.tmp{'dir' if directory else ''}"


def check_output(out, inputs=(), directory: bool = False, option: str = "--out") -> None:
    """Refuse an output that is an input (exit 2), that cannot be written
    (exit 2), or that is a directory where a file is expected (exit 3)."""
    if out is None or str(out) in ("", "-"):
        return
    p = Path(out)
    try:
        st_out = os.stat(p)
    except OSError:
        st_out = None
    if st_out is not None:
        for i in inputs:
            if i is None or str(i) in ("", "-"):
                continue
            try:
                st_in = os.stat(i)
            except OSError:
                continue
            if _same_file(st_out, st_in):
                same = "is" if os.path.abspath(i) == os.path.abspath(p) else "resolves to"
                raise OutputError(f"the output {same} the input {i}: choose another {option} "
                                  "(nothing was written)", str(out))
        import stat as _stat

        if _stat.S_ISDIR(st_out.st_mode) and not directory:
            raise InputError("is a directory; give a file name for the output", str(out))
        if not _stat.S_ISDIR(st_out.st_mode) and directory:
            raise InputError("exists and is not a directory", str(out))
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"cannot write: the directory {parent} does not exist", str(out))
    probe = temp_name(p)
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"cannot write here: {exc.strerror or exc}", str(out)) from None


# files inside an input directory that a command may read (and must never overwrite)
DATA_SUFFIXES = {".h5", ".hdf5", ".csv", ".tsv", ".txt", ".toml", ".json", ".yaml", ".yml",
                 ".ulg", ".bin", ".bag", ".mcap", ".db3", ".journal"}
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def _looks_like_data(path: str) -> bool:
    if Path(path).suffix.lower() in DATA_SUFFIXES:
        return True
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == _HDF5_MAGIC
    except OSError:
        return False


def _same_place(a: str, b: str) -> bool:
    """Same file: by inode where both exist (hard links), else by the resolved path."""
    try:
        return _same_file(os.stat(a), os.stat(b))
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_outputs_apart(named, inputs=()) -> None:
    """The outputs of one command (``named``: (option, path, directory)) must be
    distinct files (``--journal`` equal to ``--out`` lost the recording); an
    output file must not overwrite a data file inside an input directory
    (``history DIR --plot DIR/cal.h5``); a directory output must not be an input
    directory. Exit 2 before anything is written."""
    named = [(o, str(p), d) for o, p, d in named if p is not None and str(p) not in ("", "-")]
    for i, (oa, pa, _) in enumerate(named):
        for ob, pb, _ in named[i + 1:]:
            if _same_place(pa, pb):
                raise OutputError(f"{oa} and {ob} name the same file; give each its own "
                                  "(nothing was written)", pa)
    dirs = [str(i) for i in inputs if i is not None and os.path.isdir(str(i))]
    for o, p, directory in named:
        rp = os.path.realpath(p)
        for d in dirs:
            rd = os.path.realpath(d)
            if directory and rp == rd:
                raise OutputError(f"{o} is the input directory {d}; choose another (nothing "
                                  "was written)", p)
            if not directory and rp.startswith(rd + os.sep) and os.path.isfile(p) \
                    and _looks_like_data(p):
                raise OutputError(f"{o} would overwrite a file inside the input directory "
                                  f"{d}; choose another (nothing was written)", p)


def _lock_name(path: Path) -> Path:
    parent = path.parent if str(path.parent) else Path(".")
    return parent / f".{path.name}.calib-lock"


_held: dict[str, int] = {}  # lock files this process holds (re-entrant per output)


@contextlib.contextmanager
def output_lock(path):
    """Hold the output lock of ``path`` (see the module docstring); exit 3
    naming the holder when another process holds it."""
    import fcntl
    import sys

    path = Path(path)
    lock = _lock_name(path)
    key = os.path.abspath(lock)
    if key in _held:  # this process writes the same output again (nested): already held
        _held[key] += 1
        try:
            yield
        finally:
            _held[key] -= 1
        return
    for _ in range(20):
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputError(f"cannot write here: {exc.strerror or exc}", str(path)) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.pread(fd, 300, 0).decode(errors="replace").strip()
            except OSError:
                holder = ""
            os.close(fd)
            holder = " ".join(holder.split()) or "pid ?"
            raise InputError(f"another command is writing this output ({holder}); wait for "
                             "it to end or choose another --out", str(path)) from None
        # the holder before us may have removed the file after we opened it: retry on
        # the file now at that path (else two runs would each hold a lock of their own)
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except OSError:
            same = False
        if same:
            break
        os.close(fd)
    else:  # pragma: no cover - 20 removals in a row
        raise InputError("the output lock keeps changing; is another command writing it?",
                         str(path))
    try:
        cmd = " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(sys.argv))
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}: {cmd[:200]}\n".encode(errors="replace"))
    except OSError:
        pass
    _held[key] = 1
    try:
        yield
    finally:
        del _held[key]
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)


_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO, errno.EACCES,
                 errno.EPERM}


def _is_write_error(exc: OSError, paths) -> bool:
    """Whether ``exc`` comes from writing one of ``paths`` (or a file inside one)
    rather than from reading an input while an output was open."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) or "No space" in str(exc):
        return True
    if exc.filename is not None:
        f = os.path.abspath(str(exc.filename))
        return any(f == os.path.abspath(p) or f.startswith(os.path.abspath(p) + os.sep)
                   for p in paths)
    return exc.errno in _WRITE_ERRNOS


def write_error(exc: OSError, path) -> OutputError:
    """An OS error while writing an output: exit 2 naming it (a full disk says so)."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT) or "No space" in str(exc):
        return OutputError("disk full while writing; nothing was left behind", str(path))
    what = exc.strerror or type(exc).__name__
    return OutputError(f"cannot write: {what}; nothing was left behind", str(path))


@contextlib.contextmanager
def atomic_file(path):
    """``_atomic_file`` under the output lock."""
    path = Path(path)
    if path.is_dir():
        raise InputError("is a directory; give a file name for the output", str(path))
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"cannot write: the directory {parent} does not exist", str(path))
    with output_lock(path), _atomic_file(path) as tmp:
        yield tmp


@contextlib.contextmanager
def _atomic_file(path):
    """A temporary path beside ``path``, renamed onto it on success and
    removed on any failure; the file follows the umask. OS errors while
    writing are exit 2 naming the output (a full disk says so)."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise InputError("is a directory; give a file name for the output", str(path))
    if not parent.is_dir():
        raise OutputError(f"cannot write: the directory {parent} does not exist", str(path))
    clean_stale_temps(path)
    tmp = temp_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.close(fd)
    except OSError as exc:
        raise OutputError(f"cannot write here: {exc.strerror or exc}", str(path)) from None
    try:
        yield str(tmp)
        follow_umask(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if not _is_write_error(exc, (tmp, path)):
            raise  # an input's error, raised while this output was open
        raise write_error(exc, path) from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


MANIFEST = "calib-manifest.json"  # in a directory calib writes: the files it wrote there


@contextlib.contextmanager
def atomic_dir(path):
    """``_atomic_dir`` under the output lock."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if path.exists() and not path.is_dir():
        raise InputError("exists and is not a directory", str(path))
    if not parent.is_dir():
        raise OutputError(f"cannot write: the directory {parent} does not exist", str(path))
    with output_lock(path), _atomic_dir(path) as tmp:
        yield tmp


def read_manifest(path) -> dict[str, str]:
    """{file name: sha256} of the files calib wrote into directory ``path``
    (its ``calib-manifest.json``); empty when there is none."""
    import json

    m = Path(path) / MANIFEST
    if not m.is_file():
        return {}
    try:
        obj = json.loads(m.read_text(encoding="utf-8"))
        files = obj["files"] if obj.get("tool") == "calib" else None
        if not isinstance(files, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                  for k, v in files.items()):
            raise ValueError
    except (OSError, ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError):
        raise OutputError(f"{MANIFEST} there was not written by calib (or is damaged): "
                          "calib does not know which files are its own; choose another "
                          "directory (nothing was written)", str(path)) from None
    return {k: v for k, v in files.items() if k and "/" not in k and k not in (".", "..")}


def _sha256(path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@contextlib.contextmanager
def _atomic_dir(path):
    """Write a command's files into directory ``path`` (issue 37): they are made
    in a temporary directory inside it, then each is renamed into place. Only
    files calib wrote there before (listed in its ``calib-manifest.json``) are
    replaced; a file of another name is refused before anything is moved (exit
    2), and nothing else in the directory is touched. Files of the previous run
    that this run does not write are removed when unchanged since. On failure
    the temporary directory goes (and ``path``, when this call created it)."""
    import json

    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    if path.exists() and not path.is_dir():
        raise InputError("exists and is not a directory", str(path))
    if not parent.is_dir():
        raise OutputError(f"cannot write: the directory {parent} does not exist", str(path))
    created = not path.exists()
    try:
        if created:
            os.mkdir(path)
        old = read_manifest(path)
        clean_stale_temps(path / ".calib-out")
        tmp = temp_name(path / ".calib-out", directory=True)
        os.mkdir(tmp)
    except OSError as exc:
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(path)
        raise OutputError(f"cannot write here: {exc.strerror or exc}", str(path)) from None
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(path)
        raise
    try:
        yield tmp
        names = sorted(os.listdir(tmp))
        for n in names:
            if not os.path.isfile(tmp / n) or os.path.islink(tmp / n):
                raise OutputError(f"internal: {n} is not a file", str(path))
            dst = path / n
            if (os.path.lexists(dst) and n not in old) or os.path.isdir(dst) or n == MANIFEST:
                raise OutputError(f"{n} exists there and was not written by calib (no "
                                  f"{MANIFEST} lists it): nothing was written; move it or "
                                  "choose another directory", str(path))
        files = {}
        for n in names:
            files[n] = _sha256(tmp / n)
            follow_umask(tmp / n)
            os.replace(tmp / n, path / n)
        import sys
        from datetime import datetime, timezone

        man = {"tool": "calib", "command": " ".join([Path(sys.argv[0]).name] + sys.argv[1:]),
               "written_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
               "files": files}
        mtmp = tmp / MANIFEST
        mtmp.write_text(json.dumps(man, indent=1, ensure_ascii=True) + "\n", encoding="utf-8")
        follow_umask(mtmp)
        os.replace(mtmp, path / MANIFEST)
        for n, digest in old.items():  # the previous run's files this run did not write
            if n not in files:
                with contextlib.suppress(OSError):
                    if os.path.isfile(path / n) and not os.path.islink(path / n) \
                            and _sha256(path / n) == digest:
                        os.unlink(path / n)
        shutil.rmtree(tmp, ignore_errors=True)
        if created:
            follow_umask(path, directory=True)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if created:
            with contextlib.suppress(OSError):
                os.rmdir(path)  # only when empty
        if isinstance(exc, OSError) and _is_write_error(exc, (path,)):
            raise write_error(exc, path) from None
        raise


@contextlib.contextmanager
def drop_if_empty(path, created: bool):
    """On a failure, remove directory ``path`` when this command ``created`` it and
    it holds no file but calib's own hidden lock files (empty subdirectories
    go too): a full disk leaves nothing behind; outputs already written stay."""
    try:
        yield
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                for d, _, files in os.walk(path, topdown=False):
                    if d == str(path) and all(f.startswith(".calib") for f in files):
                        for f in files:
                            os.unlink(os.path.join(d, f))
                    with contextlib.suppress(OSError):
                        os.rmdir(d)  # only when empty
        raise
