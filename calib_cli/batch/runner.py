"""Run one input's chain of steps, make-like, and many inputs on an engine.

Up-to-date rule: a step's fingerprint is the SHA-256 of the tool version,
the step (name, method, options as written, output name), the SHA-256 of
every file option (the plan) and of every input artifact's bytes. It is
stored in the output (HDF5 root attribute ``batch_fingerprint``, or the
"batch" object of a JSON export). A step whose output carries the expected
fingerprint is skipped; otherwise it runs and its output replaces the old
one atomically. Because inputs are hashed by content, a re-run upstream
output re-runs what follows it, and an unchanged one does not.

Tasks and results are plain dicts of strings and numbers: that is all that
crosses to a worker process or a Dask worker. No archive content is ever
unpickled or evaluated.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import time
import uuid
from datetime import datetime, timezone
from pathlib import Path

from calib_cli import __version__
from calib_cli.batch.paths import inside
from calib_cli.batch.pipeline import Pipeline, digest, fill_placeholders
from calib_cli.batch.registry import StepRun
from calib_cli.errors import CalibError, InputError, OutputError

RAW_SUFFIXES = (".h5", ".hdf5")
LOCK_NAME = ".calib-batch.lock"
DASK_CONNECT_TIMEOUT = "15s"


def utc_now() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def read_fingerprint(path: str) -> str | None:
    """The fingerprint stored in an output, or None (missing, unreadable, foreign)."""
    p = Path(path)
    if not p.is_file():
        return None
    try:
        if p.suffix == ".json":
            with open(p, encoding="utf-8") as fh:
                obj = json.load(fh)
            v = obj.get("batch", {}).get("batch_fingerprint") if isinstance(obj, dict) else None
        else:
            import h5py

            with h5py.File(p, "r") as h5:
                v = h5.attrs.get("batch_fingerprint")
            v = v.decode() if isinstance(v, bytes) else v
        return v if isinstance(v, str) else None
    except Exception:  # any unreadable output is simply out of date
        return None


def _stamp_h5(path: str, stamp: dict) -> None:
    from calib_cli.io.h5file import h5_writer, set_attrs

    with h5_writer(path, "r+") as h5:  # a full disk: exit 2 naming it, never a crash
        set_attrs(h5, stamp)


def _source_artifacts(src: str) -> dict:
    p = Path(src)
    if not p.is_file():
        raise InputError("no such file" if not p.exists() else "not a regular file", src)
    if p.suffix.lower() in RAW_SUFFIXES:
        from calib_cli.io.h5 import open_checked

        with open_checked(src, ("raw",)):
            pass
        return {"raw": src}
    return {"source": src}


def _attr_of(path: str, name: str) -> str | None:
    """A string root attribute of an HDF5 file, or None."""
    try:
        import h5py

        with h5py.File(path, "r") as h5:
            v = h5.attrs.get(name, "")
        v = v.decode() if isinstance(v, bytes) else str(v)
        return v or None
    except Exception:
        return None


def _serial_of(path: str) -> str | None:
    return _attr_of(path, "unit_serial")


def _quiet_cli():
    """The core's warning lines (errors.warn) are dropped while a chain runs: the
    batch report carries each input's outcome. Context-local (errors.warnings_to),
    so chains in threads of one Dask worker do not share a flag."""
    from calib_cli.errors import warnings_to

    return warnings_to(None)


def run_chain(task: dict) -> dict:
    """Run one input through the pipeline. Never raises for a bad input:
    the error line goes into the result. Task keys: input, key, out,
    pipeline (Pipeline.to_dict()), force."""
    from calib_cli.io.h5 import atomic_path, sha256_file

    t0 = time.monotonic()
    pipe = Pipeline.from_dict(task["pipeline"])
    src, key, out_dir = task["input"], task["key"], task["out"]
    res = {"input": src, "key": key, "status": "failed", "steps": [], "error": None,
           "exit_code": 0, "serial": None, "outputs": {}, "steps_run": 0, "steps_skipped": 0}
    plan_of_step = [(s, s.definition(pipe.path)) for s in pipe.steps]
    failed_at, art = -1, {}  # -1: the input itself could not be read
    out = None  # the step's output being written
    try:
        with _quiet_cli():
            art = _source_artifacts(src)
            pipe_sha = pipe.sha256()
            for i, (s, d) in enumerate(plan_of_step):
                failed_at = i
                if not d.applies_to_raw_input and "source" not in art:
                    res["steps"].append({"step": s.label, "action": "not needed",
                                         "output": None})
                    continue
                missing = [n for n in d.needs if n not in art]
                if missing:
                    what = ("a CSV input needs an import step first" if "raw" in missing
                            else f"step {s.label!r} needs {', '.join(missing)}")
                    raise InputError(what, src)
                opts = dict(s.options)
                files = {}
                for fo in d.file_options:
                    if fo not in opts:  # an optional file not given
                        continue
                    v = fill_placeholders(opts[fo], src, f"step {s.index + 1}", pipe.path)
                    v = str(Path(pipe.base_dir, v)) if not Path(v).is_absolute() else v
                    if not Path(v).is_file():
                        raise InputError(f"{fo} file for step {s.label!r} not found", v)
                    opts[fo] = v
                    files[fo] = sha256_file(v)
                inputs = {n: art[n] for n in d.needs}
                fp = digest({"tool_version": __version__, "step": s.spec(), "files": files,
                              "inputs": {n: sha256_file(p) for n, p in inputs.items()}})
                out = inside(out_dir, key, s.output_name)
                rel = os.path.relpath(out, out_dir)
                if not task.get("force") and read_fingerprint(out) == fp:
                    res["steps"].append({"step": s.label, "action": "up to date", "output": rel})
                    res["steps_skipped"] += 1
                    art[d.makes] = out
                    continue
                Path(out).parent.mkdir(parents=True, exist_ok=True)
                stamp = {"batch_fingerprint": fp, "batch_pipeline_sha256": pipe_sha,
                         "batch_pipeline": pipe.name, "batch_step": s.label,
                         "batch_input": src, "batch_key": key, "batch_utc": utc_now()}
                recorded = _attr_of(art["raw"], "recorded_utc") if "raw" in art else None
                if recorded:  # when the recording was made: orders the unit's history
                    stamp["recorded_utc"] = recorded
                from calib_cli.io.outpath import check_output

                check_output(out, [src, *inputs.values(), *files])
                with atomic_path(out) as tmp:
                    run = StepRun(inputs=inputs, out=tmp, options=opts, source=src, stamp=stamp)
                    if d.name == "fit":
                        from calib_cli.batch.steps import fit_step

                        fit_step(run, d)
                    else:
                        d.function()(run)
                    if d.suffix == ".h5":
                        _stamp_h5(tmp, stamp)
                res["steps"].append({"step": s.label, "action": "ran", "output": rel})
                res["steps_run"] += 1
                art[d.makes] = out
            failed_at = None
        res["status"] = "done" if res["steps_run"] else "up to date"
    except OutputError as exc:  # a full disk: not this input's fault; the batch stops (exit 2)
        exc.path = out or exc.path
        res["error"], res["exit_code"] = exc.line(), exc.exit_code
        res["error_path"], res["error_message"] = exc.path, exc.message
    except CalibError as exc:  # the line always starts with the input it concerns
        where = f"{plan_of_step[failed_at][0].label}: " if failed_at not in (None, -1) else ""
        res["error"] = exc.line() if exc.path == src else f"{src}: {where}{exc.line()}"
        res["exit_code"] = exc.exit_code
    except Exception as exc:  # a bug in a step: still only this input fails
        res["error"] = f"{src}: internal error: {type(exc).__name__}: {exc}"
        res["exit_code"] = 70
    if failed_at == -1:
        res["steps"].append({"step": "read input", "action": "failed", "output": None})
        if Path(src).exists():  # present but broken: its old outputs are stale
            _drop_stale(out_dir, key, [st for st, _ in plan_of_step])
        # a missing input (moved, not yet synced) leaves its outputs alone
    elif failed_at is not None:
        s = plan_of_step[failed_at][0]
        res["steps"].append({"step": s.label, "action": "failed", "output": None})
        _drop_stale(out_dir, key, [st for st, _ in plan_of_step[failed_at:]])
    res["outputs"] = {k: v for k, v in art.items()} if failed_at is None else {}
    raw = res["outputs"].get("raw") if failed_at is None else None
    res["serial"] = _serial_of(raw) if raw else None
    res["seconds"] = round(time.monotonic() - t0, 3)
    return res


def _drop_stale(out_dir, key, steps) -> None:
    """After a failure, the failed step's and later steps' old outputs no longer
    match their inputs: remove them so OUT never holds a stale calibration."""
    for s in steps:
        with contextlib.suppress(OSError, InputError):
            os.unlink(inside(out_dir, key, s.output_name))


# ---------------------------------------------------------------------------
# engines


def run_tasks(tasks: list[dict], workers: int = 1, scheduler: str | None = None):
    """Yield results as inputs finish: in-process (workers=1), a local process
    pool (workers>1), or a Dask distributed cluster (scheduler address)."""
    if scheduler:
        yield from _run_dask(tasks, scheduler)
    elif workers <= 1 or len(tasks) <= 1:
        for t in tasks:
            yield run_chain(t)
    else:
        yield from _run_pool(tasks, workers)


def _lost(task: dict, why: str) -> dict:
    return {"input": task["input"], "key": task["key"], "status": "failed", "steps": [],
            "error": f"{task['input']}: {why}", "exit_code": 70, "serial": None,
            "outputs": {}, "steps_run": 0, "steps_skipped": 0, "seconds": 0.0}


def _preload(task: dict) -> None:
    """Import the steps' modules (numpy, scipy, h5py, ...) once here, so that
    forked workers start with them instead of each importing them again."""
    import contextlib

    for s in Pipeline.from_dict(task["pipeline"]).steps:
        with contextlib.suppress(Exception):
            s.definition().function()
    with contextlib.suppress(Exception):
        import calib_cli.batch.steps  # noqa: F401
        import calib_cli.io.apply_file  # noqa: F401
        import calib_cli.io.contract_json  # noqa: F401
        import calib_cli.io.csvlog  # noqa: F401
        import calib_cli.io.h5  # noqa: F401


def _run_pool(tasks, workers):
    from concurrent.futures import ProcessPoolExecutor, as_completed

    _preload(tasks[0])
    with ProcessPoolExecutor(max_workers=workers) as ex:
        futs = {ex.submit(run_chain, t): t for t in tasks}
        for f in as_completed(futs):
            try:
                yield f.result()
            except Exception as exc:  # the worker process died (e.g. out of memory)
                yield _lost(futs[f], f"worker process failed: {type(exc).__name__}: {exc}")


def _run_dask(tasks, scheduler):
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'calib-cli[dask]'") from None
    try:
        client = Client(scheduler, timeout=DASK_CONNECT_TIMEOUT)
    except (OSError, TimeoutError) as exc:
        raise InputError(f"cannot reach the Dask scheduler: {exc}", scheduler) from None
    except (TypeError, ValueError) as exc:  # e.g. tls:// without certificates configured
        raise InputError(f"cannot connect to the Dask scheduler ({exc}); for tls:// set the "
                         "Dask TLS configuration (docs/batch.md)", scheduler) from None
    try:
        run_id = uuid.uuid4().hex[:12]  # keys unique per run: runs may share a cluster
        futs = client.map(run_chain, tasks, pure=False,
                          key=[f"calib-batch-{run_id}-{i}" for i in range(len(tasks))])
        index = {f.key: t for f, t in zip(futs, tasks, strict=True)}
        for f in as_completed(futs):
            try:
                yield f.result()
            except Exception as exc:  # worker lost, task erred outside run_chain
                yield _lost(index[f.key], f"Dask task failed: {type(exc).__name__}: {exc}")
    finally:
        client.close()


# ---------------------------------------------------------------------------
# lock


@contextlib.contextmanager
def output_lock(out_dir: str):
    """An exclusive flock on OUT/.calib-batch.lock for the whole run. The kernel
    drops it when the process ends, so a killed run never leaves a stale lock."""
    path = Path(out_dir) / LOCK_NAME
    try:  # never through a symlink: the lock file is truncated below
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as exc:
        raise InputError(f"cannot open the lock file: {exc.strerror}", str(path)) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = ""
            with contextlib.suppress(OSError):
                holder = Path(path).read_text().strip()
            raise InputError("another calib batch is running on this output directory"
                             + (f" ({holder})" if holder else ""), str(out_dir)) from None
        with contextlib.suppress(OSError):  # the holder's line is a courtesy (a full disk)
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()} since {utc_now()}\n".encode())
        yield
    finally:
        os.close(fd)
