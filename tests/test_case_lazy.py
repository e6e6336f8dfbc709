"""Fields left in their files (``read_field(lazy=True)``): a task with ``every > 1`` reads its ``from``,
reference and baseline files block by block, never whole, and gets the results of a whole read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from xarray.backends import netCDF4_

import latticedft as ldft
from latticedft import lagrangians
from latticedft._serve import _stream
from latticedft.io.fields import read_field

from case_helpers import run_wave_every
from helpers import membrane_field, wave_field


@pytest.fixture
def reads(monkeypatch):
    """Every read of a netCDF variable: ``(folder/file name, variable, shape read)``."""
    seen: list[tuple[str, str, tuple[int, ...]]] = []
    original = netCDF4_.NetCDF4ArrayWrapper._getitem

    def record(self, key):
        out = original(self, key)
        path = Path(self.datastore._filename)
        seen.append((f"{path.parent.name}/{path.name}", self.variable_name, np.shape(out)))
        return out

    monkeypatch.setattr(netCDF4_.NetCDF4ArrayWrapper, "_getitem", record)
    return seen


def _longest(reads, name: str, ndim: int = 2) -> int:
    """The most time slices one read of ``psi`` (``ndim`` dims) in file ``name`` (``folder/file``) took (0: it
    was not read)."""
    sizes = [shape[0] if len(shape) == ndim else 1 for f, v, shape in reads if f.endswith(name) and v == "psi"]
    return max(sizes, default=0)


def _small_blocks(slice_bytes: int, slices: int = 4) -> None:
    """Blocks of ``slices`` slices for the NaN scan, the comparisons and the serving window."""
    size = slices * slice_bytes
    ldft.set_options(scan_bytes=size, task_block_bytes=size, serve_window_bytes=size)


def test_a_lazy_read_leaves_the_values_in_the_file_and_gives_the_same_field(tmp_path, reads):
    field = membrane_field(n=6, nt=30)
    field.to_netcdf(tmp_path / "f.nc")
    _small_blocks(6 * 8 * 8, slices=5)
    lazy = read_field(tmp_path / "f.nc", lazy=True)
    assert not lazy.variable._in_memory
    assert 0 < _longest(reads, "/f.nc", 3) <= 5  # the NaN/inf scan read blocks of 5 slices
    whole = read_field(tmp_path / "f.nc")
    assert whole.variable._in_memory
    xr.testing.assert_identical(lazy.load(), whole)


def test_the_nan_scan_in_blocks_gives_the_error_of_a_whole_read(tmp_path):
    field = wave_field(nx=9, nt=40)
    values = field.values.copy()
    values[23, 4] = np.nan  # in the fifth block of 5 slices
    values[37, 2] = np.inf
    field.copy(data=values).to_netcdf(tmp_path / "bad.nc")
    ldft.set_options(scan_bytes=5 * 9 * 8)
    with pytest.raises(ldft.InputError) as whole:
        read_field(tmp_path / "bad.nc")
    with pytest.raises(ldft.InputError) as lazy:
        read_field(tmp_path / "bad.nc", lazy=True)
    assert str(lazy.value) == str(whole.value)
    assert "holds 2 NaN/inf value(s), the first at index t=23, x=4" in str(lazy.value)
    assert len(str(lazy.value).splitlines()) == 1


@pytest.mark.parametrize("make, every", [(lambda: wave_field(nx=17, nt=45), 6), (lambda: membrane_field(8, 25), 4)])
def test_a_dirichlet_field_left_in_its_file_is_served_as_the_whole_field(tmp_path, reads, make, every):
    field = make()
    field.to_netcdf(tmp_path / "init.nc")
    slice_bytes = int(np.prod(field.shape[1:])) * 8
    _small_blocks(slice_bytes)
    model = lagrangians.wave(1.0)
    whole = ldft.serve(model, field, every=1)
    init = read_field(tmp_path / "init.nc", lazy=True)
    reads.clear()
    thin = ldft.serve(model, init, every=every)
    idx = _stream.kept_slices(field.sizes["t"], every)
    assert thin.field["slice"].values.tolist() == idx.tolist()
    np.testing.assert_array_equal(thin.field.values, whole.field.values[idx])
    np.testing.assert_array_equal(thin.field["t"].values, whole.field["t"].values[idx])
    # the strips are read block by block, in the window's chunks (4 slices), never the whole field
    assert 0 < _longest(reads, "/init.nc", field.ndim) <= 4
    assert not init.variable._in_memory


def test_a_lazy_init_with_too_few_slices_for_its_strips_is_refused(tmp_path):
    wave_field(nx=9, nt=12).to_netcdf(tmp_path / "short.nc")
    init = read_field(tmp_path / "short.nc", lazy=True)
    with pytest.raises(ldft.InputError, match=r"^init: holds 12 time slices but the Dirichlet boundary"):
        ldft.serve(lagrangians.wave(1.0), init, slices=30, every=4)


def test_a_case_task_with_every_reads_its_files_block_by_block(tmp_path, capsys, reads):
    whole, whole_ds = run_wave_every(tmp_path, capsys, 1)
    nt_file = read_field(Path(__file__).parents[1] / "cases" / "wave" / "data" / "test.nc").sizes["t"]
    assert _longest(reads, "data/test.nc") == nt_file  # every = 1: the field is read whole
    slice_bytes = int(np.prod(whole_ds["psi"].shape[1:])) * 8
    _small_blocks(slice_bytes)
    reads.clear()
    thin, thin_ds = run_wave_every(tmp_path, capsys, 7)
    # from (also the reference) and baseline: blocks of at most 4 slices, the first two, or one kept slice
    assert 0 < _longest(reads, "data/test.nc") <= 4
    assert 0 < _longest(reads, "data/test_leapfrog.nc") <= 4
    idx = _stream.kept_slices(60, 7)
    for name in ("psi", "psi_ref", "psi_err", "baseline_err_max", "baseline_err_rms", "extrapolation"):
        np.testing.assert_array_equal(thin_ds[name].values, whole_ds[name].isel(t=idx).values, err_msg=name)
    assert thin["max_error"] == whole["max_error"] and thin["compared_slices"] == whole["compared_slices"]
    assert thin["rms_error"] == pytest.approx(whole["rms_error"], rel=1e-12)  # summed block by block
    for key, value in whole["baseline"].items():
        assert thin["baseline"][key] == (value if "max" in key or key in ("file", "slices") else pytest.approx(value))


def test_the_memory_check_counts_the_kept_slices(tmp_path):
    from latticedft._case import load_case
    from latticedft._run import check_case
    from latticedft._run._guards import check_task_memory

    from case_helpers import tiny_wave

    case = tiny_wave(tmp_path)
    plain = load_case(case)
    values = 30 * 13 * 8  # the task's field in bytes
    with pytest.raises(ldft.ConfigError, match="30 slices of 13 values"):
        check_task_memory(plain, check_case(plain), available=2 * values)
    thin = load_case(case, ["serve.test.every=10"])
    check_task_memory(thin, check_case(thin), available=2 * values)  # 4 kept slices, 4 copies
    with pytest.raises(ldft.ConfigError, match="4 kept slices of 13 values"):
        check_task_memory(thin, check_case(thin), available=values // 10)
