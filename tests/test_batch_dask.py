"""calib batch on a Dask distributed cluster bound to loopback (issue 10):
the same archive gives byte-identical calibration parameters.

Needs the optional extra calib-cli[dask] (dask + distributed); skipped
without it."""

from __future__ import annotations

import h5py
import pytest

pytest.importorskip("distributed", reason="dask/distributed not installed: the optional extra "
                                          "calib-cli[dask] (pip install 'calib-cli[dask]')")

import contextlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402

from calib_cli.cli.main import main  # noqa: E402
from calib_cli.validation.archive import make_archive  # noqa: E402


def run_cli(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0
    return code, out.getvalue(), err.getvalue()


def batch_json(pipe, inputs, out, *extra):
    code, so, se = run_cli("batch", pipe, *inputs, "--out", out, "--json", *extra)
    return code, (json.loads(so) if so.strip() else None), se


def _cluster(processes: bool):
    from distributed import LocalCluster

    return LocalCluster(n_workers=2, threads_per_worker=1, processes=processes,
                        host="127.0.0.1", dashboard_address="127.0.0.1:0", protocol="tcp")


@pytest.fixture
def cluster():
    """Workers as threads of this process (fast: nothing to import), still
    reached over TCP on loopback through the scheduler."""
    with _cluster(processes=False) as c:
        yield c


@pytest.fixture
def process_cluster():
    """Worker processes, as on a real cluster."""
    with _cluster(processes=True) as c:
        yield c


def _params_bytes(path) -> dict:
    with h5py.File(path) as h5:
        return {f"{g}/{k}": h5[g][k][()].tobytes() for g in ("params", "sigma") for k in h5[g]}


def _compare(n, n_broken, tmp_path, cluster):
    a = make_archive(tmp_path, n=n, n_broken=n_broken)
    assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
    c1, local, _ = batch_json(a["pipeline"], [a["archive"]], tmp_path / "local")
    c2, dask, se = batch_json(a["pipeline"], [a["archive"]], tmp_path / "dask",
                              "--scheduler", cluster.scheduler_address)
    assert c1 == c2 == 1, se
    assert dask["summary"] == local["summary"]
    assert dask["summary"]["failed"] == n_broken
    lr = {r["input"]: r for r in local["inputs"]}
    for r in dask["inputs"]:
        assert r["status"] == lr[r["input"]]["status"]
        assert r["error"] == lr[r["input"]]["error"]
        if r["status"] == "failed":
            continue
        assert _params_bytes(tmp_path / "dask" / r["outputs"]["calibration"]) == \
            _params_bytes(tmp_path / "local" / r["outputs"]["calibration"])
    # and the second run on the cluster executes nothing
    c3, again, _ = batch_json(a["pipeline"], [a["archive"]], tmp_path / "dask",
                              "--scheduler", cluster.scheduler_address)
    assert again["summary"]["steps_run"] == 0


def test_dask_cluster_byte_identical(tmp_path, cluster):
    _compare(10, 3, tmp_path, cluster)


@pytest.mark.slow
def test_dask_cluster_byte_identical_50(tmp_path, process_cluster):
    _compare(50, 3, tmp_path, process_cluster)


def test_unreachable_scheduler_is_one_line(tmp_path, monkeypatch):
    from calib_cli.batch import runner

    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT", "2s")
    a = make_archive(tmp_path, n=1, n_broken=0)
    code, so, se = run_cli("batch", a["pipeline"], a["archive"], "--out", tmp_path / "o",
                           "--scheduler", "tcp://127.0.0.1:9")
    assert code == 3 and "cannot reach the Dask scheduler" in se
    assert "Traceback" not in se


def test_tls_scheduler_without_certificates_is_one_line(tmp_path, monkeypatch):
    """tls:// with no TLS configuration: exit 3, one line (was an internal error)."""
    from calib_cli.batch import runner

    monkeypatch.setattr(runner, "DASK_CONNECT_TIMEOUT", "2s")
    a = make_archive(tmp_path, n=1, n_broken=0)
    code, so, se = run_cli("batch", a["pipeline"], a["archive"], "--out", tmp_path / "o",
                           "--scheduler", "tls://127.0.0.1:9")
    assert code == 3 and "Dask" in se, se
    assert len(se.strip().splitlines()) == 1 and "Traceback" not in se
