"""Import time: ``import latticedft`` and ``latticedft --help`` load neither torch nor xarray; the file formats'
libraries (pyvista, matplotlib, meshio) and scipy's ODE solvers load only when used; on a terminal the first
line shows while the engine loads. Each check runs in a fresh Python (this process has everything loaded)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}


def _loaded(code: str) -> set[str]:
    """The top-level modules loaded after running ``code`` in a fresh Python."""
    script = textwrap.dedent(code) + "\nimport sys\nprint(' '.join(sorted({m.split('.')[0] for m in sys.modules})))\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=ENV, timeout=300)
    assert out.returncode == 0, out.stderr
    return set(out.stdout.split())


HEAVY = {"torch", "xarray", "scipy", "pandas", "pyvista", "matplotlib", "meshio", "netCDF4", "h5py"}


def test_import_latticedft_is_light_and_names_load_on_use() -> None:
    assert not _loaded("import latticedft") & HEAVY
    loaded = _loaded(
        """
        import latticedft as ldft
        assert {"features", "mlp", "polynomial"} <= set(ldft.MODELS) and callable(ldft.learn)
        assert ldft.lagrangians.wave and ldft.systems.make_field and ldft.__version__
        from latticedft import serve, InputError
        assert "learn" in dir(ldft) and "systems" in dir(ldft)
        """
    )
    assert {"torch", "xarray"} <= loaded and not loaded & {"pyvista", "matplotlib", "meshio"}


def test_help_and_usage_errors_load_no_engine() -> None:
    loaded = _loaded(
        """
        from latticedft.cli import main
        assert main(["--help"]) == 0
        assert main(["run", "--help"]) == 0
        assert main(["no-such-command"]) == 2
        """
    )
    assert not loaded & HEAVY, loaded & HEAVY


def test_formats_and_ode_solvers_load_on_use() -> None:
    loaded = _loaded("import latticedft.io, latticedft.systems, latticedft.io.exporters")
    assert not loaded & {"pyvista", "matplotlib", "meshio", "torch"}
    assert "scipy.integrate" not in _loaded_full("import latticedft.systems")
    assert "scipy.integrate" in _loaded_full("from latticedft import systems; systems.oscillator_sin(1.0, n=3)")
    assert "pyvista" in _loaded("from latticedft.io import write_paraview")


def _loaded_full(code: str) -> set[str]:
    script = textwrap.dedent(code) + "\nimport sys\nprint(' '.join(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=ENV, timeout=300)
    assert out.returncode == 0, out.stderr
    return set(out.stdout.split())


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_first_line_at_once_on_a_terminal(tmp_path: Path) -> None:
    from helpers import on_a_terminal

    code, text = on_a_terminal([sys.executable, "-m", "latticedft", "check", str(tmp_path / "missing")], ENV)
    assert code == 1
    assert text.startswith("latticedft: loading torch and xarray ...\r\x1b[K"), text
    assert text.split("\x1b[K", 1)[1].strip().startswith("latticedft: error:")  # the one error line after it
