"""Open every kind of ParaView export with ParaView's own readers (pvpython).

Skipped when ``pvpython`` is not on PATH (Debian: ``apt-get install paraview``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from latticedft.io import write_paraview

pytestmark = [
    pytest.mark.paraview,
    pytest.mark.skipif(shutil.which("pvpython") is None, reason="pvpython not found"),
]

# Runs inside pvpython: open each file, step through its time steps, report what ParaView sees.
PV_SCRIPT = textwrap.dedent(
    """
    import json, sys
    from paraview.simple import OpenDataFile

    report = {}
    for path in json.load(open(sys.argv[1])):
        reader = OpenDataFile(path)
        if reader is None:
            report[path] = {"error": "no reader"}
            continue
        times = [float(t) for t in (reader.TimestepValues or [])]
        steps = []
        for t in times or [None]:
            if t is None:
                reader.UpdatePipeline()
            else:
                reader.UpdatePipeline(t)
            info = reader.GetDataInformation()
            ranges = {name: list(reader.PointData[name].GetRange(-1 if
                      reader.PointData[name].GetNumberOfComponents() > 1 else 0))
                      for name in reader.PointData.keys()}
            steps.append({"points": info.GetNumberOfPoints(), "cells": info.GetNumberOfCells(),
                          "ranges": ranges})
        report[path] = {"class": reader.GetXMLName(), "times": times, "steps": steps,
                        "field_data": list(reader.FieldData.keys())}
    print("REPORT" + json.dumps(report))
    """
)


def _lattice(shape: tuple[int, ...], dims: tuple[str, ...], comps: list[str] | None = None) -> xr.DataArray:
    rng = np.random.default_rng(1)
    coords: dict[str, object] = {d: np.arange(n) * 0.5 for d, n in zip(dims, shape)}
    full = shape + ((len(comps),) if comps else ())
    if comps:
        coords["component"] = comps
    return xr.DataArray(
        rng.standard_normal(full), coords=coords, name="psi", dims=dims + (("component",) if comps else ())
    )


def _run_pvpython(tmp_path: Path, files: list[Path]) -> dict[str, dict]:
    script = tmp_path / "check.py"
    script.write_text(PV_SCRIPT)
    listing = tmp_path / "files.json"
    listing.write_text(json.dumps([str(f) for f in files]))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.setdefault("QT_QPA_PLATFORM", "offscreen")
    proc = subprocess.run(
        [shutil.which("pvpython") or "pvpython", "--force-offscreen-rendering", str(script), str(listing)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        cwd=tmp_path,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("REPORT")]
    assert proc.returncode == 0 and lines, (
        f"pvpython failed (rc={proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    )
    # ParaView prints reader errors/warnings (e.g. unsupported file versions) to stderr.
    assert "ERROR" not in proc.stderr, proc.stderr[-3000:]
    return json.loads(lines[-1][len("REPORT") :])


def test_paraview_opens_every_export(tmp_path: Path) -> None:
    out = tmp_path / "results"
    fields = {
        "wave": _lattice((6, 9), ("t", "x")),
        "plate": _lattice((4, 5, 7), ("t", "y", "x")),
        "cube": _lattice((3, 2, 3, 4), ("t", "z", "y", "x")),
        "flow": _lattice((3, 4, 5), ("t", "y", "x"), ["u", "v"]),
        "osc": _lattice((15,), ("t",)),
        "orbit": _lattice((25,), ("t",), ["x", "y"]),
    }
    fields["orbit"][20:] = np.nan  # stopped early: 20 points remain
    written: dict[str, list[Path]] = {}
    for stem, psi in fields.items():
        written[stem] = write_paraview(out, stem, psi, {"psi_ref": psi.fillna(0.0) * 2})
    all_files = [f for files in written.values() for f in files]
    report = _run_pvpython(tmp_path, all_files)
    assert set(report) == {str(f) for f in all_files}
    for path, rep in report.items():
        assert "error" not in rep, (path, rep)
        for step in rep["steps"]:
            assert {"psi", "psi_ref"} <= set(step["ranges"]), (path, step)

    def collection(stem: str) -> dict:
        return report[str(out / f"{stem}.pvd")]

    for stem in ("wave", "plate", "cube", "flow"):
        psi = fields[stem]
        rep = collection(stem)
        assert rep["times"] == pytest.approx(psi.t.values), stem
        n_points = int(np.prod([psi.sizes[d] for d in psi.dims[1:] if d != "component"]))
        assert [s["points"] for s in rep["steps"]] == [n_points] * psi.sizes["t"], stem
        assert "TimeValue" in rep["field_data"]
        if "component" not in psi.dims:
            for i, step in enumerate(rep["steps"]):
                frame = psi.isel(t=i).values
                assert step["ranges"]["psi"] == pytest.approx([frame.min(), frame.max()])
        for f in written[stem][1:]:
            if f.suffix == ".vtr" and "spacetime" not in f.name:
                assert report[str(f)]["steps"][0]["points"] == n_points

    st = report[str(out / "wave_spacetime.vtr")]
    assert st["steps"][0]["points"] == 6 * 9 and st["steps"][0]["cells"] == 5 * 8

    osc = collection("osc")
    assert osc["times"] == pytest.approx(fields["osc"].t.values)
    assert [s["points"] for s in osc["steps"]] == list(range(1, 16))
    orbit = collection("orbit")
    assert [s["points"] for s in orbit["steps"]] == [min(i + 1, 20) for i in range(25)]
    whole = report[str(out / "orbit.vtp")]["steps"][0]
    assert whole["points"] == 20 and whole["cells"] == 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__, "-v"]))
