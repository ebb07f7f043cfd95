"""The PBD peer harness (``tools/bench_pbd_peer.py``, issue 21 item 6) on a CPU-sized grid: its
grid and surface are a valid closed body, and a run reports the wsim sweep against its own
converged run (and, without Newton installed, says the Newton half was skipped)."""

from __future__ import annotations

import importlib.util
import json
import pathlib
import subprocess
import sys

import numpy as np
import trimesh

TOOL = pathlib.Path(__file__).resolve().parents[1] / "tools" / "bench_pbd_peer.py"


def _tool():
    spec = importlib.util.spec_from_file_location("bench_pbd_peer", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_grid_is_a_closed_outward_body_of_positive_tets() -> None:
    tool = _tool()
    dims, cell = (4, 2, 3), 0.05
    points, tets = tool.soft_grid(dims, cell)
    assert len(points) == 5 * 3 * 4 and len(tets) == 5 * 4 * 2 * 3
    p, q, r, s = (points[tets[:, i]] for i in range(4))
    vol = np.einsum("ij,ij->i", np.cross(q - p, r - p), s - p) / 6.0
    np.testing.assert_allclose(np.abs(vol).sum(), np.prod(dims) * cell ** 3, rtol=1e-12)  # the cells, once each
    order, faces, tets_new, n_surface = tool.boundary_surface(points, tets)
    mesh = trimesh.Trimesh(points[order][:n_surface], faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    np.testing.assert_allclose(mesh.volume, np.prod(dims) * cell ** 3, rtol=1e-12)  # > 0: outward
    assert faces.max() < n_surface and tets_new.max() == len(points) - 1


def test_a_run_reports_the_sweep_against_its_converged_run() -> None:
    out = subprocess.run([sys.executable, str(TOOL), "--device", "cpu", "--dims", "4,2,2", "--frames", "20",
                          "--sweep", "4x1,16x4", "--reference", "32x8", "--levels", "0.5"],
                         capture_output=True, text=True, timeout=600, check=True)
    lines = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    wsim_rows = [r for r in lines if r.get("solver") == "wsim" and not r.get("reference")]
    assert [(r["substeps"], r["iterations"]) for r in wsim_rows] == [(4, 1), (16, 4)]
    assert all(r["physical"] for r in wsim_rows)
    assert wsim_rows[1]["error"] < wsim_rows[0]["error"]  # more work, closer to the converged run
    try:
        import newton  # noqa: F401
    except ImportError:
        assert any(r.get("solver") == "newton" and "skipped" in r for r in lines)
    summary = [r for r in lines if "summary" in r]
    assert len(summary) == 1
    ranges = [r for r in lines if "range" in r]
    if ranges:  # both solvers ran: the worst ratio over the range is no better than at any listed level
        listed = [e["newton_over_wsim_time"] for e in summary[0]["summary"] if "newton_over_wsim_time" in e]
        assert all(ranges[0]["worst_newton_over_wsim_time"] <= x + 1e-12 for x in listed)
        assert ranges[0] is lines[-1]
