"""Candidate fits on a real Dask cluster (``--scheduler tcp://...``), local to this host.

The cluster is a ``distributed.LocalCluster`` with worker processes, listening on 127.0.0.1 only; the
diagnosis connects to its scheduler address exactly as a user connects to a remote cluster. Its answer
must be the one the local process pool gives on the same traces.
"""

from __future__ import annotations

import json

import pytest

from virtualaxis.cli.main import main
from virtualaxis.diagnosis.bench import all_cases, generate_case

distributed = pytest.importorskip("distributed", reason="dask[distributed] is part of the dev extras")


@pytest.fixture(scope="module")
def cluster():
    from distributed import LocalCluster
    from distributed.diagnostics.plugin import SchedulerPlugin

    class CountFits(SchedulerPlugin):
        def __init__(self, owner):
            self.owner = owner

        def transition(self, key, start, finish, *args, **kwargs):
            if finish == "memory" and str(key).startswith("_safe_fit"):
                self.owner.done_fits += 1

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, silence_logs=40) as c:
        c.done_fits = 0
        c.scheduler.add_plugin(CountFits(c), name="count-fits")
        yield c


@pytest.fixture(scope="module")
def rigid_case(tmp_path_factory):
    out = tmp_path_factory.mktemp("dask_case")
    case = next(c for c in all_cases() if c.name == "rigid-coulomb")
    meta = generate_case(case, out / "case", seed=5, quick=True)
    return out, meta


@pytest.mark.slow
def test_diagnosis_on_a_dask_cluster_matches_the_process_pool(cluster, rigid_case, capsys):
    out, meta = rigid_case
    common = ["diagnose", "--config", str(out / "case" / "nominal.toml"), *meta["files"]["fit"],
              "--holdout", *meta["files"]["holdout"], "--no-hybrid"]
    assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
    rc = main([*common, "--out", str(out / "dask"), "--scheduler", cluster.scheduler_address])
    assert rc == 0, capsys.readouterr().err
    assert "conclusion: coulomb_friction" in capsys.readouterr().out
    rc = main([*common, "--out", str(out / "pool"), "--jobs", "2"])
    assert rc == 0
    dask_rep = json.loads((out / "dask" / "report.json").read_text())
    pool_rep = json.loads((out / "pool" / "report.json").read_text())
    assert dask_rep["accepted"] == pool_rep["accepted"] == ["coulomb_friction"]

    def params(rep):
        return {(e["name"], k): v["value"] for e in rep["effects"] for k, v in e["params"].items()}

    assert params(dask_rep) == pytest.approx(params(pool_rep), rel=1e-9)
    # the cluster's workers did the fitting: the scheduler saw the candidate-fit tasks finish
    assert cluster.done_fits >= 2


def test_unreachable_scheduler_is_a_clear_error(rigid_case, capsys):
    import socket

    with socket.socket() as s:  # a free port with nobody listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out, meta = rigid_case
    rc = main(["diagnose", "--config", str(out / "case" / "nominal.toml"), *meta["files"]["fit"],
               "--out", str(out / "o"), "--scheduler", f"tcp://127.0.0.1:{port}", "--no-hybrid"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: --scheduler tcp://127.0.0.1:") and "Traceback" not in err
