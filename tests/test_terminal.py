"""Terminal and notebook: log lines through tqdm.write, no tqdm.auto (the Jupyter warning), few refreshes where a
bar cannot redraw, every term of a model on request, error and invariant over time."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from tqdm.std import tqdm

import latticedft as ldft
from latticedft import lagrangians, systems
from latticedft._progress import progress_bar
from latticedft.cli._terminal import TqdmHandler

from case_helpers import oscillator_case, run_cli

REPO = Path(__file__).resolve().parents[1]


def test_log_lines_go_through_tqdm_write() -> None:
    stream = io.StringIO()
    bar = tqdm(total=10, desc="serve", file=stream, mininterval=0)
    bar.update(3)
    handler = TqdmHandler(stream)
    logger = logging.getLogger("latticedft.test_terminal")
    logger.addHandler(handler)
    try:
        logger.warning("a warning line")
    finally:
        logger.removeHandler(handler)
        bar.close()
    text = stream.getvalue()
    # the bar was cleared, the line written whole on its own line, and the bar drawn again after it
    assert text.count("a warning line\n") == 1
    before, after = text.split("a warning line\n", 1)
    assert before.endswith("\r") and "3/10" in before  # the bar, then cleared back to the line start
    assert "3/10" in after and "serve" in after


def test_import_in_a_jupyter_kernel_without_ipywidgets_does_not_warn() -> None:
    script = textwrap.dedent(
        """
        import sys, types, warnings
        warnings.simplefilter("error")
        class ZMQInteractiveShell:
            config = {"IPKernelApp": {}}
        ip = types.ModuleType("IPython"); ip.get_ipython = lambda: ZMQInteractiveShell()
        disp = types.ModuleType("IPython.display"); disp.display = print; ip.display = disp
        sys.modules.update({"IPython": ip, "IPython.display": disp, "ipykernel": types.ModuleType("ipykernel"),
                            "ipykernel.zmqshell": types.ModuleType("ipykernel.zmqshell")})
        import latticedft
        from latticedft._progress import in_jupyter, progress_bar
        assert in_jupyter()
        bar = progress_bar(5, "x", True)  # no ipywidgets: the plain bar, no warning
        bar.update(5); bar.close()
        assert not any(m in sys.modules for m in ("tqdm.auto", "tqdm.autonotebook", "tqdm.notebook")), sys.modules
        print("ok")
        """
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_a_plain_bar_refreshes_rarely(capsys) -> None:
    train = [systems.oscillator_wells(a, n=101, dt=0.5) for a in (1.7, 1.2, 0.6)]
    model = ldft.MLPLagrangian(hidden=[8], activation="tanh", form="kinetic-potential")
    ldft.learn(model, train, max_iter=100, progress=True)
    ldft.serve(model, train[0], progress=True)
    err = capsys.readouterr().err
    redraws = err.count("\r") + err.count("\n")
    assert "train (lbfgs)" in err and "100/100" in err and "99/99" in err
    assert redraws <= 8, err  # was one per L-BFGS chunk and serving update (~21)
    ldft.learn(ldft.MLPLagrangian(hidden=[8], form="kinetic-potential"), train, max_iter=5)
    assert capsys.readouterr().err == ""  # progress=None: not a terminal, no bar
    assert progress_bar(3, "x", False).disable


def test_describe_all_terms() -> None:
    train = [systems.oscillator_wells(a, n=101, dt=0.5) for a in (1.7, 1.2, 0.6)]
    model = ldft.PolynomialLagrangian(orders=(4, 8), time_symmetric=True)
    ldft.learn(model, train)
    short, full = str(model), model.describe(max_terms=None)
    n_short = sum(1 for ln in short.splitlines() if ln.startswith("      +") or ln.startswith("      -"))
    n_full = sum(1 for ln in full.splitlines() if ln.startswith("      +") or ln.startswith("      -"))
    assert n_short == 12 and n_full > 12
    assert f"... {n_full - 12} more terms, smaller (use --all" in short and "more terms" not in full
    # the largest first
    coefs = [
        abs(float(ln.split()[0])) for ln in short.splitlines() if ln.startswith("      ") and ln.split()[0][0] in "+-"
    ]
    assert coefs == sorted(coefs, reverse=True)
    assert model.describe(max_terms=3).count("\n      +") + model.describe(max_terms=3).count("\n      -") == 3


def test_info_all(tmp_path: Path, capsys) -> None:
    case = oscillator_case(tmp_path)  # polynomial (4, 8): 45 terms
    assert run_cli(capsys, "train", case, "-q")[0] == 0
    code, out, _ = run_cli(capsys, "info", case)
    assert code == 0 and "more terms, smaller (use --all" in out
    code, out_all, _ = run_cli(capsys, "info", case, "--all")
    assert code == 0 and "more terms" not in out_all and len(out_all.splitlines()) > len(out.splitlines())


def test_error_and_invariant_vs_time() -> None:
    ref = systems.wave_string([(1, 1.0), (2, 0.4, 0.3)], nx=21, nt=81)
    model = ldft.PolynomialLagrangian(orders=(2, 2))
    ldft.learn(model, systems.wave_string([(1, 1.0), (3, 0.3)], nx=21, nt=41))
    pred = ldft.serve(model, ref).field
    err = ldft.error_vs_time(pred, ref)
    assert err.dims == ("t", "metric") and list(err["metric"].values) == ["max", "rms"]
    assert err.sizes["t"] == 81 and np.allclose(err["t"], ref["t"])
    total = ldft.compare(pred, ref)
    assert float(err.sel(metric="max").max()) == pytest.approx(total["max_error"], rel=1e-12)
    rms_all = float(np.sqrt((err.sel(metric="rms") ** 2).mean()))
    assert rms_all == pytest.approx(total["rms_error"], rel=1e-12)
    assert float(err.isel(t=0).sel(metric="max")) == 0.0  # the initial slices are given
    with pytest.raises(ldft.InputError, match="shapes"):
        ldft.error_vs_time(pred, ref.isel(x=slice(0, 5)))
    energy = ldft.invariant_vs_time(ldft.serve(lagrangians.wave(), ref).field, systems.wave_energy)
    assert energy.dims == ("t",) and energy.attrs["relative_drift"] < 1e-12  # leapfrog conserves it
    assert ldft.invariant_vs_time(pred, systems.wave_energy).attrs["relative_drift"] > 0
    with pytest.raises(ldft.InputError, match="invariant"):
        ldft.invariant_vs_time(pred, lambda f: f.values)
