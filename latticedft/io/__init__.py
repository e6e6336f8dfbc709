"""Field files (netCDF) and the export formats of a run: ParaView files, figures, XDMF/HDF5 series.

The formats by name are :data:`latticedft.io.exporters.EXPORTERS`.

>>> from latticedft.io import read_field, write_field, write_paraview, write_xdmf
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from latticedft.io.fields import COMPONENT_DIM as COMPONENT_DIM
from latticedft.io.fields import field_periodic as field_periodic
from latticedft.io.fields import field_spacing as field_spacing
from latticedft.io.fields import lattice_dims as lattice_dims
from latticedft.io.fields import read_field as read_field
from latticedft.io.fields import validate_field as validate_field
from latticedft.io.fields import write_field as write_field

if TYPE_CHECKING:
    from latticedft.io.figures import plot_prediction as plot_prediction
    from latticedft.io.figures import task_figure as task_figure
    from latticedft.io.vtk import read_pvd as read_pvd
    from latticedft.io.vtk import write_paraview as write_paraview
    from latticedft.io.vtk import write_pvd as write_pvd
    from latticedft.io.xdmf import read_xdmf as read_xdmf
    from latticedft.io.xdmf import write_xdmf as write_xdmf

__all__ = [
    "COMPONENT_DIM",
    "field_periodic",
    "field_spacing",
    "lattice_dims",
    "read_field",
    "validate_field",
    "write_field",
    "read_pvd",
    "write_paraview",
    "write_pvd",
    "plot_prediction",
    "task_figure",
    "write_xdmf",
    "read_xdmf",
]


def __getattr__(name: str):  # pyvista, matplotlib and meshio are imported only when their files are wanted
    if name in ("read_pvd", "write_paraview", "write_pvd"):
        from latticedft.io import vtk

        return getattr(vtk, name)
    if name in ("plot_prediction", "task_figure"):
        from latticedft.io import figures

        return getattr(figures, name)
    if name in ("write_xdmf", "read_xdmf"):
        from latticedft.io import xdmf

        return getattr(xdmf, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
