"""latticedft: learn discrete field theories from lattice data and serve them.

The method is H. Qin, "Machine learning and serving of discrete field
theories", Sci. Rep. 10, 19329 (2020): learn a discrete Lagrangian density
``L_d`` whose discrete Euler–Lagrange equations the data obey, then predict
new solutions by solving those equations slice by slice — a variational
(symplectic) integrator nobody wrote by hand.

>>> import latticedft as ldft
>>> sorted(ldft.MODELS)
['features', 'mlp', 'polynomial', 'sparse']
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# The public names are imported on first use (PEP 562): `import latticedft` itself is instant, so the
# command line answers --help and starts its first line before torch and xarray are loaded. The names,
# and the module each comes from:
_PUBLIC: dict[str, str] = {
    "action": "._action",
    "del_residual": "._action",
    "DeviceWarning": "._device",
    "ConfigError": "._errors",
    "InputError": "._errors",
    "LatticeDFTError": "._errors",
    "ModelFileError": "._errors",
    "ServeError": "._errors",
    "LatticeField": "._lattice",
    "as_lattice_field": "._lattice",
    "GAUGES": "._learn",
    "LearnReport": "._learn",
    "diagnose": "._learn",
    "learn": "._learn",
    "NoiseEstimate": "._learn",
    "denoise": "._learn",
    "estimate_noise": "._learn",
    "load_model": "._modelfile",
    "save_model": "._modelfile",
    "MODELS": "._models",
    "PRESETS": "._models",
    "AbstractLagrangian": "._models",
    "AnalyticLagrangian": "._models",
    "EnsembleLagrangian": "._models",
    "FeatureLagrangian": "._models",
    "SparseLagrangian": "._models",
    "Library": "._models",
    "LinearLagrangian": "._models",
    "MLPLagrangian": "._models",
    "ModelKind": "._models",
    "PolynomialLagrangian": "._models",
    "get_options": "._options",
    "set_options": "._options",
    "limit_threads": "._threads",
    "DiscoveryReport": "._noether",
    "Symmetry": "._noether",
    "SymmetryReport": "._noether",
    "builtin_symmetries": "._noether",
    "discover_symmetries": "._noether",
    "discrete_energy": "._noether",
    "noether_charge": "._noether",
    "noether_charges": "._noether",
    "relative_drift": "._noether",
    "symmetries": "._noether",
    "SelectionReport": "._select",
    "select": "._select",
    "ServeOptions": "._serve",
    "ServeResult": "._serve",
    "calibration": "._serve",
    "compare": "._serve",
    "error_vs_time": "._serve",
    "invariant_vs_time": "._serve",
    "serve": "._serve",
    "Stencil": "._stencil",
}
#: Subpackages and modules reachable as attributes (``ldft.systems``) without importing them first.
_SUBMODULES = ("cli", "io", "lagrangians", "systems", "testing")

__all__ = sorted([*_PUBLIC, "lagrangians", "__version__"])


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name], __name__), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f".{name}", __name__)
    elif name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            value = version("latticedft")
        except PackageNotFoundError:  # pragma: no cover - running from a source tree
            value = "0+unknown"
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # once imported, a plain attribute
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_PUBLIC, *_SUBMODULES, "__version__"})


if TYPE_CHECKING:  # the names for type checkers and editors
    from . import lagrangians as lagrangians
    from ._action import action as action
    from ._action import del_residual as del_residual
    from ._device import DeviceWarning as DeviceWarning
    from ._errors import ConfigError as ConfigError
    from ._errors import InputError as InputError
    from ._errors import LatticeDFTError as LatticeDFTError
    from ._errors import ModelFileError as ModelFileError
    from ._errors import ServeError as ServeError
    from ._lattice import LatticeField as LatticeField
    from ._lattice import as_lattice_field as as_lattice_field
    from ._learn import GAUGES as GAUGES
    from ._learn import LearnReport as LearnReport
    from ._learn import NoiseEstimate as NoiseEstimate
    from ._learn import denoise as denoise
    from ._learn import diagnose as diagnose
    from ._learn import estimate_noise as estimate_noise
    from ._learn import learn as learn
    from ._modelfile import load_model as load_model
    from ._modelfile import save_model as save_model
    from ._models import MODELS as MODELS
    from ._models import PRESETS as PRESETS
    from ._models import AbstractLagrangian as AbstractLagrangian
    from ._models import AnalyticLagrangian as AnalyticLagrangian
    from ._models import EnsembleLagrangian as EnsembleLagrangian
    from ._models import FeatureLagrangian as FeatureLagrangian
    from ._models import Library as Library
    from ._models import LinearLagrangian as LinearLagrangian
    from ._models import MLPLagrangian as MLPLagrangian
    from ._models import ModelKind as ModelKind
    from ._models import PolynomialLagrangian as PolynomialLagrangian
    from ._models import SparseLagrangian as SparseLagrangian
    from ._noether import DiscoveryReport as DiscoveryReport
    from ._noether import Symmetry as Symmetry
    from ._noether import SymmetryReport as SymmetryReport
    from ._noether import builtin_symmetries as builtin_symmetries
    from ._noether import discover_symmetries as discover_symmetries
    from ._noether import discrete_energy as discrete_energy
    from ._noether import noether_charge as noether_charge
    from ._noether import noether_charges as noether_charges
    from ._noether import relative_drift as relative_drift
    from ._noether import symmetries as symmetries
    from ._options import get_options as get_options
    from ._options import set_options as set_options
    from ._select import SelectionReport as SelectionReport
    from ._select import select as select
    from ._serve import ServeOptions as ServeOptions
    from ._serve import ServeResult as ServeResult
    from ._serve import calibration as calibration
    from ._serve import compare as compare
    from ._serve import error_vs_time as error_vs_time
    from ._serve import invariant_vs_time as invariant_vs_time
    from ._serve import serve as serve
    from ._stencil import Stencil as Stencil
    from ._threads import limit_threads as limit_threads

    __version__: str
