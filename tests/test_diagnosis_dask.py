"""Candidate fits on a real Dask cluster (``--scheduler tcp://...``), local to this host.

The cluster is a ``distributed.LocalCluster`` with worker processes, listening on 127.0.0.1 only; the
diagnosis connects to its scheduler address exactly as a user connects to a remote cluster. Its answer
must be the one the local process pool gives on the same traces.
"""

from __future__ import annotations

import json

import background
import pytest

from virtualaxis.cli.main import main
from virtualaxis.diagnosis.bench import all_cases, generate_case

distributed = pytest.importorskip("distributed", reason="dask[distributed] is part of the dev extras")


@pytest.fixture(scope="module")
def rigid_case(tmp_path_factory):
    out = tmp_path_factory.mktemp("dask_case")
    case = next(c for c in all_cases() if c.name == "rigid-coulomb")
    meta = generate_case(case, out / "case", seed=5, quick=True)
    return out, meta


@pytest.mark.slow
@pytest.mark.background("dask_vs_pool")
def test_diagnosis_on_a_dask_cluster_matches_the_process_pool(request):
    """``virtualaxis diagnose --scheduler tcp://...`` on a ``LocalCluster`` and ``--jobs 2`` on the same case,
    run in the background (tests/background.py, ``dask_vs_pool``)."""
    job = background.result(request.config, "dask_vs_pool")
    out = job["out"]
    assert job["scheduler_address"].startswith("tcp://127.0.0.1:")
    rc, text, err = job["dask"]
    assert rc == 0, err
    assert "conclusion: coulomb_friction" in text
    assert job["pool"][0] == 0, job["pool"][2]
    dask_rep = json.loads((out / "dask" / "report.json").read_text())
    pool_rep = json.loads((out / "pool" / "report.json").read_text())
    assert dask_rep["accepted"] == pool_rep["accepted"] == ["coulomb_friction"]

    def params(rep):
        return {(e["name"], k): v["value"] for e in rep["effects"] for k, v in e["params"].items()}

    assert params(dask_rep) == pytest.approx(params(pool_rep), rel=1e-9)
    # the cluster's workers did the fitting: the scheduler saw the candidate-fit tasks finish
    assert job["done_fits"] >= 2


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
