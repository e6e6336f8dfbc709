"""Small case folders for the command-line tests (generated in tmp_path, seconds to run)."""

from __future__ import annotations

import hashlib
import shutil
import textwrap
from pathlib import Path

import numpy as np

from latticedft import systems
from latticedft.cli import main
from latticedft.io import write_field

REPO = Path(__file__).resolve().parents[1]
WAVE = REPO / "cases" / "wave"
# Keep the wave case quick in tests: 60 served slices, 6 ParaView frames, one thread.
FAST = ["--set", "serve.test.slices=60", "--set", "export.max_frames=6", "--set", "run.threads=1"]


def copy_wave(tmp: Path) -> Path:
    dest = tmp / "wave"
    shutil.copytree(WAVE, dest, ignore=shutil.ignore_patterns("results", "results.tmp*"))
    return dest


def write_toml(case: Path, text: str) -> Path:
    case.mkdir(parents=True, exist_ok=True)
    (case / "case.toml").write_text(textwrap.dedent(text))
    return case


def tiny_wave(tmp: Path, name: str = "tiny") -> Path:
    """A 1+1D string: train 20 x 13, test 30 x 13 (whole field, Dirichlet)."""
    case = tmp / name
    (case / "data").mkdir(parents=True)
    write_field(case / "data" / "train.nc", {"psi": systems.wave_string([(1, 1.0), (2, 0.4)], nx=13, nt=20)})
    write_field(case / "data" / "test.nc", {"psi": systems.wave_string([(1, 0.5, 0.3), (3, 0.2)], nx=13, nt=30)})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [2, 0]
        [train]
        data = ["data/train.nc"]
        [[serve]]
        name = "test"
        from = "data/test.nc"
        [run]
        threads = 1
        [export]
        max_frames = 4
        """,
    )
    return case


def oscillator_case(tmp: Path) -> Path:
    """Paper Example 1 in 1D; task `outside` starts far outside the training range and stops part-way."""
    case = tmp / "osc"
    (case / "data").mkdir(parents=True)
    for i, a in enumerate((1.2, 0.6)):
        write_field(case / "data" / f"train{i}.nc", {"psi": systems.oscillator_sin(a, n=51)})
    write_field(case / "data" / "inside.nc", {"psi": systems.oscillator_sin(-0.6, n=51)})
    write_field(case / "data" / "outside.nc", {"psi": systems.make_field([3.0, 3.0], ("t",), spacing=1.0)})
    write_toml(
        case,
        """
        [model]
        kind = "polynomial"
        orders = [4, 8]
        [train]
        data = ["data/train*.nc"]
        [[serve]]
        name = "outside"
        from = "data/outside.nc"
        slices = 100
        [[serve]]
        name = "inside"
        from = "data/inside.nc"
        [run]
        threads = 1
        """,
    )
    return case


def run_cli(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def snapshot(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` (to show that nothing was touched)."""
    if not folder.exists():
        return {}
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def leftovers(case: Path) -> list[str]:
    return sorted(p.name for p in case.iterdir() if p.name.startswith("results.tmp"))


def nan_field(path: Path) -> None:
    psi = systems.wave_string([(1, 1.0)], nx=13, nt=20)
    psi[5, 4] = np.nan
    write_field(path, {"psi": psi})


def run_wave_every(tmp_path: Path, capsys, every: int):
    """Run a copy of cases/wave with task `test` served at `every`; its summary record and its loaded task file."""
    import json

    import xarray as xr

    case = copy_wave(tmp_path / f"every{every}")
    sets = ["--set", f"serve.test.every={every}", "--set", "export.formats=[]"]
    code, _, err = run_cli(capsys, "run", case, "-q", *FAST, *sets)
    assert code == 0, err
    res = case / "results"
    summary = json.loads((res / "summary.json").read_text())
    with xr.open_dataset(res / "test.nc", engine="netcdf4", decode_times=False) as ds:
        ds = ds.load()
    return summary["tasks"]["test"], ds
