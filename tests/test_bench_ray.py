"""kneas-bench on Ray: a local Ray instance (2 CPUs, no dashboard) runs cells; a failure is recorded, the rest go on."""

from __future__ import annotations

import json
import sys

import pytest

from kneas_method.bench import backends, grid
from kneas_method.bench.cells import cell_dir, is_complete

from test_bench import FAKE_TRAIN, _calls  # noqa: E402  (tests/ is on sys.path under pytest)

ray = pytest.importorskip("ray")


def test_ray_backend_runs_cells_and_records_failures(tmp_path, monkeypatch):
    script = tmp_path / "fake_train.py"
    script.write_text(FAKE_TRAIN)
    prefix = (sys.executable, str(script))
    log = tmp_path / "calls.jsonl"
    monkeypatch.setenv("FAKE_LOG", str(log))
    monkeypatch.setenv("FAKE_FAIL", "jaw/k-neas/2/0")  # Ray workers inherit the environment of ray.init
    out = tmp_path / "bench"
    cells = grid.grid(["foot", "jaw"], ["k-neas"], (2,), (None,), (0,), "tiny") + [grid.Cell("foot", "fdk", None, None, 0, "tiny")]

    backend = backends.RayBackend(num_cpus=2)
    seen = []
    results = backend.run(cells, out, prefix, on_result=lambda c, r: seen.append((c.id, r.status)))
    assert not ray.is_initialized()  # the instance it started is shut down again
    status = {r.cell_id: r.status for r in results}
    assert status == {"foot__k-neas__K2__vall__s0__tiny": "done", "jaw__k-neas__K2__vall__s0__tiny": "failed",
                      "foot__fdk__K-__vall__s0__tiny": "done"}
    assert sorted(seen) == sorted(status.items())
    record = json.loads((cell_dir(out, cells[1]) / "cell.json").read_text())
    assert record["status"] == "failed" and "boom in jaw/k-neas/2/0" in record["error"]
    assert len(_calls(log)) == 3

    # a rerun would run only the failed cell (the rerun itself is tested with the local backend)
    assert [c.id for c in cells if not is_complete(out, c)] == [cells[1].id]
