"""The case templates of ``latticedft new``: a case.toml with a comment on every key, a make_data.py that makes
the data with :mod:`latticedft.systems`, and a README stub. Each is small: its ``latticedft run`` takes
seconds.

``{name}`` in a text is the new case's folder name (the texts are ``str.format`` templates, so literal
braces are doubled).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Template", "TEMPLATES", "DEFAULT_TEMPLATE"]


@dataclass(frozen=True)
class Template:
    """One template: what it is (one line), and the three files it writes."""

    what: str
    #: the data files make_data.py writes, one ``file: what`` per line
    data: str
    case_toml: str
    make_data: str
    readme: str


_HEADER = """\
# {name}: {what}
# Written by `latticedft new {name} --like {like}`. Edit it, then `latticedft run {name}`.
# Every key but [train] data is optional; the case.toml reference (docs/case-toml.md of latticedft) lists them.
"""

_README = """\
# {name}

{what}. Written by `latticedft new {name} --like {like}`.

```bash
latticedft check {name}     # validate case.toml and data/ (writes nothing)
latticedft run {name}       # train, serve every [[serve]] task, export into {name}/results/
latticedft info {name}      # the learned L_d and the scores
```

- `case.toml`: the model, the training data, the serving tasks (every key is commented).
- `make_data.py`: writes `data/` with `latticedft.systems`:
{data_list}
  replace them with your own observed fields (netCDF, variable `psi`, time first:
  `latticedft.systems.make_field` and `latticedft.io.write_field`), then `python make_data.py`.
- `results/`: written by `latticedft run` (`--overwrite` to replace it): `summary.json` holds the numbers,
  `<task>.nc` the served field, its reference and the error, `<task>.pvd` opens in ParaView and
  `<task>.png` is a figure.
"""

_MAKE_DATA_HEAD = '''\
"""Write data/ for the case {name}: {what}.

    python make_data.py

{data_lines}
Deterministic; replace the fields with your own observations (same layout: time first, x last).
"""

from __future__ import annotations

from pathlib import Path

from latticedft import systems
from latticedft.io import write_field

HERE = Path(__file__).resolve().parent
'''

_MAKE_DATA_FOOT = """

def main() -> None:
    data = HERE / "data"
    data.mkdir(exist_ok=True)
    for file, field in fields().items():
        write_field(data / file, {{"psi": field}}, history="{name}/make_data.py")
        print(f"wrote data/{{file}} {{dict(field.sizes)}}")


if __name__ == "__main__":
    main()
"""

WAVE = Template(
    what="the wave equation psi_tt = psi_xx on a string with fixed ends",
    data="data/train.nc: one observed string, 21 sites, 81 slices (one period of its lowest mode)\n"
    "data/test.nc: another solution (other amplitudes and phases), 161 slices, to predict",
    case_toml=_HEADER
    + """
[field]
variable = "psi"                # the data variable of every field file in data/

[model]
kind = "polynomial"             # L_d linear in its coefficients: learned exactly, in one least-squares step
orders = [2, 2]                 # degree in the differences and in the stencil mean: the wave L_d's class

[train]
data = ["data/train.nc"]        # the observed fields to learn from (globs allowed: "data/train_*.nc")
gauge = "unit-mass"             # the gauge of L_d: "unit-mass", "trace" or "auto" (see the reference)

[[serve]]
name = "test"                   # the task: results/test.nc, test.pvd, test.png
from = "data/test.nc"           # its first two slices and fixed ends start the prediction; also the reference
slices = 161                    # time slices served, the two initial ones included: 160 steps
boundary = "dirichlet"          # the ends are held at the values of data/test.nc
invariant = "latticedft.systems:wave_energy"   # an energy over t; its drift goes to results/summary.json

[run]
threads = 1                     # torch and BLAS threads (one is fastest for small cases and shared machines)

[export]
formats = ["paraview", "figures"]   # per task: a ParaView time series and a PNG ([]: none; "xdmf": large runs)
max_frames = 40                 # most ParaView frames per task, evenly spread
""",
    make_data=_MAKE_DATA_HEAD
    + '''NX = 21  # sites on [0, 1]: dx = 1/20, dt = dx/2


def fields() -> dict:
    """File name -> field: one observed string, and another one to predict (other amplitudes, twice as long)."""
    train = systems.wave_string([(1, 1.0), (2, 0.5, 0.3), (3, 0.25, 1.0)], nx=NX, nt=81)  # one period
    test = systems.wave_string([(1, 0.6, 0.5), (2, -0.4), (3, 0.15, 0.7)], nx=NX, nt=161)
    return {{"train.nc": train, "test.nc": test}}
'''
    + _MAKE_DATA_FOOT,
    readme=_README,
)

OSCILLATOR = Template(
    what="a nonlinear oscillator, 2 (sin psi + 1) psi'' + psi'^2 cos psi + pi^2/200 psi = 0 (Qin 2020, Example 1)",
    data="data/train_*.nc: three observed trajectories, psi(0) = 0.4, 0.8, 1.2, 51 points (dt = 1)\n"
    "data/test.nc: an unseen trajectory, psi(0) = -0.6, to predict",
    case_toml=_HEADER
    + """
[field]
variable = "psi"                # the data variable of every field file in data/

[model]
kind = "polynomial"             # L_d = sum a_pq d^p s^q (difference d, mean s): learned exactly
orders = [4, 8]                 # maximum degree in the difference and in the mean: 45 terms

[train]
data = ["data/train_*.nc"]      # three observed trajectories (globs are expanded and sorted)
gauge = "unit-mass"             # the gauge of L_d: "unit-mass", "trace" or "auto" (see the reference)
ridge = "auto"                  # Tikhonov weight picked by the held-out residual (leave one trajectory out)

[[serve]]
name = "test"                   # the task: results/test.nc, test.pvd, test.png
from = "data/test.nc"           # an unseen trajectory: its first two points start the prediction
slices = 51                     # time slices served, the two initial ones included: 50 steps
charges = ["energy"]            # the learned L_d's discrete energy over t: its drift is drawn in test.png

[run]
threads = 1                     # torch and BLAS threads (one is fastest for small cases and shared machines)

[export]
formats = ["paraview", "figures"]   # per task: a ParaView time series and a PNG ([]: none)
""",
    make_data=_MAKE_DATA_HEAD
    + '''

def fields() -> dict:
    """File name -> field: three observed trajectories (dt = 1) and an unseen one to predict."""
    out = {{f"train_{{a:.2f}}.nc": systems.oscillator_sin(a, n=51, dt=1.0) for a in (0.4, 0.8, 1.2)}}
    out["test.nc"] = systems.oscillator_sin(-0.6, n=51, dt=1.0)
    return out
'''
    + _MAKE_DATA_FOOT,
    readme=_README,
)

KEPLER = Template(
    what="orbits in the Sun's gravity, r'' = -r / |r|^3 (Qin 2020, Sec. 4), with a neural L_d",
    data="data/train_*.nc: three observed orbits (launch distance and speed in the name), dt = 0.05\n"
    "data/test.nc: an unseen launch (r = 1, v = 0.93), 301 slices, to predict",
    case_toml=_HEADER
    + """
[field]
variable = "psi"                # the data variable: positions psi(t, component), component = ["x", "y"]

[model]
kind = "mlp"                    # a neural L_d, trained by L-BFGS
preset = "radial"               # L_d = |q1 - q0|^2 / (2 dt^2) - (V(q0) + V(q1)) / 2, V a network of 1/|q|
hidden = [8, 8]                 # hidden layer sizes of V (the preset's are [32, 32]; small is quick)
seed = 0                        # seed of the initial weights

[train]
data = ["data/train_*.nc"]      # three observed orbits, one period each
max_iter = 80                   # L-BFGS iterations (more: a better fit, a longer run)
max_time = 60                   # ... or stop after this many seconds

[[serve]]
name = "test"                   # the task: results/test.nc, test.pvd, test.png
from = "data/test.nc"           # an unseen launch: its first two positions start the orbit
slices = 301                    # time slices served, the two initial ones included: 300 steps
box = 10.0                      # an orbit that leaves |x|, |y| <= 10 stops there (complete)
charges = ["rotation-xy", "energy"]   # angular momentum and energy over t: their drift is drawn in test.png

[run]
threads = 1                     # torch and BLAS threads (one is fastest for small cases and shared machines)

[export]
formats = ["paraview", "figures"]   # per task: ParaView polylines and a PNG ([]: none)
""",
    make_data=_MAKE_DATA_HEAD
    + '''

def fields() -> dict:
    """File name -> field: three orbits launched at distance r with speed v, and an unseen launch."""
    out = {{
        f"train_{{r:.2f}}_{{v:.2f}}.nc": systems.kepler_orbit(r, v, dt=0.05)
        for r, v in ((1.0, 1.0), (1.0, 0.85), (0.8, 1.25))
    }}
    out["test.nc"] = systems.kepler_orbit(1.0, 0.93, dt=0.05, n=301)
    return out
'''
    + _MAKE_DATA_FOOT,
    readme=_README,
)

FIELD_2D = Template(
    what="the wave equation psi_tt = psi_xx + psi_yy on a membrane with a fixed frame (2+1D)",
    data="data/train.nc: one observed membrane, 17 x 17 sites, 31 slices\n"
    "data/test.nc: another solution (other modes), 61 slices, to predict",
    case_toml=_HEADER
    + """
[field]
variable = "psi"                # the data variable of every field file: psi(t, y, x)

[model]
kind = "polynomial"             # L_d linear in its coefficients: learned exactly, in one least-squares step
orders = [2, 2]                 # degree in the three differences and in the stencil mean: the wave L_d's class

[train]
data = ["data/train.nc"]        # the observed fields to learn from (globs allowed)
gauge = "unit-mass"             # the gauge of L_d: "unit-mass", "trace" or "auto" (see the reference)

[[serve]]
name = "test"                   # the task: results/test.nc, test.pvd, test.png
from = "data/test.nc"           # its first two slices and its frame start the prediction; also the reference
slices = 61                     # time slices served, the two initial ones included: 60 steps
boundary = "dirichlet"          # the frame is held at the values of data/test.nc
invariant = "latticedft.systems:wave_energy"   # an energy over t; its drift goes to results/summary.json

[run]
threads = 1                     # torch and BLAS threads (one is fastest for small cases and shared machines)

[export]
formats = ["paraview", "figures"]   # per task: a ParaView time series and a PNG ([]: none; "xdmf": large runs)
max_frames = 30                 # most ParaView frames per task, evenly spread
""",
    make_data=_MAKE_DATA_HEAD
    + '''N = 17  # sites per side of the unit square


def fields() -> dict:
    """File name -> field: one observed membrane, and another one to predict (other modes, longer)."""
    train = systems.wave_membrane([(1, 1, 1.0), (2, 1, 0.5, 0.3), (1, 2, 0.3, 1.0)], nx=N, ny=N, nt=31)
    test = systems.wave_membrane([(1, 1, 0.6, 0.5), (2, 2, 0.25), (1, 2, 0.2, 0.7)], nx=N, ny=N, nt=61)
    return {{"train.nc": train, "test.nc": test}}
'''
    + _MAKE_DATA_FOOT,
    readme=_README,
)

#: ``--like`` name -> template.
TEMPLATES: dict[str, Template] = {"wave": WAVE, "oscillator": OSCILLATOR, "kepler": KEPLER, "field-2d": FIELD_2D}
DEFAULT_TEMPLATE = "wave"
