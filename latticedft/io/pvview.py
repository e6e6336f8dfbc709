"""A pvpython script per task, ``<task>_view.py``: part of the ``paraview`` export format.

The script opens the task's ParaView files, colours the field by its variable
with a labelled colour bar, warps it (Warp By Scalar) for 1+1D space-time and
2+1D fields, shows 1D frames as a line chart (Plot Over Line for 2+1D and
3+1D) and, run as ``pvpython <task>_view.py --screenshot out.png``, saves a
picture of its views. On a machine without a display ParaView's offscreen
rendering may crash (Debian's build: SIGSEGV in ``XSync``); run it under a
virtual X server: ``xvfb-run -a pvpython <task>_view.py --screenshot out.png``.
With ``--nc`` it reads the task file ``<task>.nc`` through ParaView's netCDF CF
reader instead of the ``.pvd`` frames.

The script needs only ParaView (its own Python); what it shows is fixed when
it is written (file names, array names, labels with units).
"""

from __future__ import annotations

import os
import pprint
from pathlib import Path
from typing import Any

import xarray as xr

from latticedft._atomic import write_text_atomic
from latticedft.io._labels import coord_label, quantity_label
from latticedft.io.fields import COMPONENT_DIM, lattice_dims

__all__ = ["write_view_script", "view_settings"]


def view_settings(stem: str, field: xr.DataArray, *, has_reference: bool = False) -> dict[str, Any]:
    """What the script of task ``stem`` shows: the kind of view, the files, the array names and labels."""
    var = str(field.name) if field.name is not None else "psi"
    dims = lattice_dims(field)
    space = list(dims[1:])
    comps = (
        ([str(c) for c in field.coords[COMPONENT_DIM].values] if COMPONENT_DIM in field.coords else [])
        if COMPONENT_DIM in field.dims
        else []
    )
    if not space:
        kind = "orbit" if len(comps) >= 2 else "series"
    else:
        kind = {1: "spacetime", 2: "grid2", 3: "grid3"}[len(space)]
    labels = {f"{d}_label": coord_label(field, d) for d in space[::-1][:3]}
    first = f"_{comps[0]}" if comps and space else ""
    settings: dict[str, Any] = {
        "name": stem,
        "variable": var,
        "kind": kind,
        "t_dim": dims[0],
        "space_dims": space,
        "label": quantity_label(field, var, first),
        "t_label": coord_label(field, dims[0]),
        "x_label": "x",
        "y_label": "y",
        "z_label": "z",
        "c_labels": [quantity_label(field, var, f"_{c}") for c in comps[:3]],
        "has_reference": bool(has_reference),
        "pvd": f"{stem}.pvd",
        "spacetime": f"{stem}_spacetime.vtr",
        "vtp": f"{stem}.vtp",
        "nc": f"{stem}.nc",
    }
    # VTK x is the last lattice dim, y the one before it, z the one before that
    for axis, dim in zip("xyz", space[::-1]):
        settings[f"{axis}_label"] = labels[f"{dim}_label"]
    return settings


def write_view_script(
    folder: str | os.PathLike[str], stem: str, field: xr.DataArray, *, has_reference: bool = False
) -> Path:
    """Write ``<stem>_view.py`` into ``folder`` (atomically) and return its path."""
    settings = view_settings(stem, field, has_reference=has_reference)
    text = _TEMPLATE.format(
        name=stem,
        variable=settings["variable"],
        kind=settings["kind"],
        task=pprint.pformat(settings, indent=4, width=100, sort_dicts=False),
    )
    return write_text_atomic(Path(folder) / f"{stem}_view.py", text)


# The script; str.format fills {name}, {variable}, {kind} and {task}; literal braces are doubled.
_TEMPLATE = r'''"""Show the served task {name!r} in ParaView: the field coloured by {variable}, with its reference.

Written by latticedft next to the task's ParaView files (the ``paraview`` export format).

    pvpython {name}_view.py --screenshot {name}_view.png     # a picture, then exit
    xvfb-run -a pvpython {name}_view.py --screenshot out.png  # the same on a machine without a display
    pvpython {name}_view.py --nc --screenshot out.png         # read {name}.nc (every served slice) instead
    paraview --script={name}_view.py                          # the same views in the ParaView window

Options: ``--time T`` shows the slice nearest to time T (default: the last served one), ``--size W H``
sets the screenshot's size in pixels. What it shows ({kind}):

* 1+1D: the space-time surface ({name}_spacetime.vtr) warped by {variable} and coloured by it, and a line
  chart of {variable} and {variable}_ref against x at one time (the {name}.pvd frames);
* 2+1D: the frame at one time warped by {variable} (Warp By Scalar) and coloured by it, and {variable},
  {variable}_ref along a line through the middle (Plot Over Line);
* 3+1D: the middle slice of the frame at one time, coloured by {variable}, and Plot Over Line along x;
* 1D: {variable} and {variable}_ref against time as a line chart ({name}.vtp); an orbit in its plane,
  coloured by time, with the reference orbit in grey.

``--nc`` reads the task file {name}.nc with ParaView's netCDF CF reader ("NetCDF Reader": Dimensions set
to the lattice's spatial dims, Spherical Coordinates off) instead of the .pvd frames: every served slice,
one file (no space-time surface; lattice fields only).
"""

import argparse
import os
import sys

from paraview.simple import (
    AssignViewToLayout,
    Calculator,
    ColorBy,
    CreateLayout,
    CreateView,
    GetAnimationScene,
    GetColorTransferFunction,
    GetScalarBar,
    NetCDFReader,
    OpenDataFile,
    PlotOverLine,
    Render,
    SaveScreenshot,
    Show,
    Slice,
    Text,
    WarpByScalar,
)

TASK = {task}
HERE = os.path.dirname(os.path.abspath(__file__))


def _file(name):
    path = os.path.join(HERE, name)
    if not os.path.isfile(path):
        sys.exit("{{}}: file not found; run `latticedft export` with the paraview format first".format(path))
    return path


def _colour(display, view, array, title, association="POINTS"):
    ColorBy(display, (association, array))
    display.RescaleTransferFunctionToDataRange(True, False)
    display.SetScalarBarVisibility(view, True)
    bar = GetScalarBar(GetColorTransferFunction(array), view)
    bar.Title = title
    bar.ComponentTitle = ""
    bar.TitleFontSize = 14
    bar.LabelFontSize = 12


def _axes(display, x, y, z=""):
    grid = display.DataAxesGrid
    grid.GridAxesVisibility = 1
    grid.XTitle, grid.YTitle, grid.ZTitle = x, y, z


def _title(view, text):
    label = Text(Text=text)
    shown = Show(label, view)
    shown.WindowLocation = "Upper Center"
    shown.FontSize = 16


def _chart(xtitle, ytitle, title, x_range):
    """A line chart; its x axis a little wider than ``x_range`` (the last tick label is otherwise cut off at
    the view's edge)."""
    view = CreateView("XYChartView")
    view.BottomAxisTitle = xtitle
    view.LeftAxisTitle = ytitle
    view.ChartTitle = title
    view.LegendLocation = "TopRight"
    # ParaView 5.11's default chart font (Arial) draws the tick labels doubled and clipped in offscreen
    # renderings; Times does not
    view.LeftAxisLabelFontFamily = view.BottomAxisLabelFontFamily = "Times"
    lo, hi = x_range
    pad = 0.03 * (hi - lo) if hi > lo else 0.5
    view.BottomAxisUseCustomRange = 1
    view.BottomAxisRangeMinimum, view.BottomAxisRangeMaximum = lo - pad, hi + pad
    return view


def _lines(display, arrays, x_array):
    display.UseIndexForXAxis = 0
    display.XArrayName = x_array
    colours = {{TASK["variable"]: ("1", "0", "0"), TASK["variable"] + "_ref": ("0", "0.3", "1")}}
    visibility, colour, style = [], [], []
    for name in arrays:
        visibility += [name, "1"]
        colour += [name, *colours.get(name, ("0", "0", "0"))]
        style += [name, "1" if name == TASK["variable"] else "2"]
    display.SeriesVisibility = visibility
    display.SeriesColor = colour
    display.SeriesLineStyle = style


def _reader(args):
    """The frames: the .pvd collection, or the task file through the netCDF CF reader."""
    if args.nc:
        reader = NetCDFReader(FileName=[_file(TASK["nc"])])
        reader.Dimensions = "(" + ", ".join(TASK["space_dims"]) + ")"
        reader.SphericalCoordinates = 0
        reader.ReplaceFillValueWithNan = 1
        reader.UpdatePipelineInformation()
        return reader
    return OpenDataFile(_file(TASK["pvd"]))


def _time(reader, args):
    times = list(reader.TimestepValues or [])
    if not times:
        return None
    t = times[-1] if args.time is None else min(times, key=lambda v: abs(v - args.time))
    scene = GetAnimationScene()
    scene.UpdateAnimationUsingDataTimeSteps()
    scene.AnimationTime = t
    return t


def _warp_scale(lo, hi, extent):
    amplitude = max(abs(lo), abs(hi))
    return 0.25 * extent / amplitude if amplitude > 0 else 1.0


def _oblique(view, source, azimuth=0.0):
    """Look at the warped surface from the front (low y), above it, turned by ``azimuth`` degrees."""
    b = source.GetDataInformation().GetBounds()
    centre = [(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2]
    size = max(b[1] - b[0], b[3] - b[2], b[5] - b[4], 1e-12)
    view.CameraFocalPoint = centre
    view.CameraPosition = [centre[0], centre[1] - 1.8 * size, centre[2] + 1.6 * size]
    view.CameraViewUp = [0.0, 0.0, 1.0]
    view.ResetCamera()
    if azimuth:
        view.GetActiveCamera().Azimuth(azimuth)
        view.ResetCamera()


def lattice_views(args):
    var, n_space = TASK["variable"], len(TASK["space_dims"])
    render = None if (n_space == 1 and args.nc) else CreateView("RenderView")
    if n_space == 1 and not args.nc:
        surface = OpenDataFile(_file(TASK["spacetime"]))
        surface.UpdatePipeline()
        lo, hi = surface.PointData[var].GetRange()
        b = surface.GetDataInformation().GetBounds()
        warp = WarpByScalar(Input=surface, Scalars=["POINTS", var], Normal=[0, 0, 1], UseNormal=1)
        warp.ScaleFactor = _warp_scale(lo, hi, max(b[1] - b[0], b[3] - b[2]))
        display = Show(warp, render)
        _colour(display, render, var, TASK["label"])
        _axes(display, TASK["x_label"], TASK["t_label"], "{{}} (warped x {{:.3g}})".format(var, warp.ScaleFactor))
        _oblique(render, warp, -20.0)
        _title(render, "{{}}: {{}} over space-time, warped by its value".format(TASK["name"], var))
    frames = _reader(args)
    t = _time(frames, args)
    frames.UpdatePipeline(t if t is not None else 0.0)
    b = frames.GetDataInformation().GetBounds()
    lo, hi = frames.PointData[var].GetRange()
    mid = [(b[0] + b[1]) / 2, (b[2] + b[3]) / 2, (b[4] + b[5]) / 2]
    arrays = [a for a in (var, var + "_ref") if a in frames.PointData.keys()]
    when = "{{}} = {{:.4g}}".format(TASK["t_dim"], t) if t is not None else ""
    if n_space == 1:
        chart = _chart(TASK["x_label"], TASK["label"], "{{}}: {{}}".format(TASK["name"], when), b[:2])
        along = Calculator(Input=frames)  # the frame's x as an array: the chart's x axis
        along.Function = "coordsX"
        along.ResultArrayName = "x_coordinate"
        _lines(Show(along, chart), arrays, "x_coordinate")
        return render, chart  # from the task file (--nc): the chart alone
    if n_space == 2:
        warp = WarpByScalar(Input=frames, Scalars=["POINTS", var], Normal=[0, 0, 1], UseNormal=1)
        warp.ScaleFactor = _warp_scale(lo, hi, max(b[1] - b[0], b[3] - b[2]))
        display = Show(warp, render)
        _colour(display, render, var, TASK["label"])
        _axes(display, TASK["x_label"], TASK["y_label"], "{{}} (warped x {{:.3g}})".format(var, warp.ScaleFactor))
        _oblique(render, warp, -25.0)
        _title(render, "{{}}: {{}} at {{}}, warped by its value".format(TASK["name"], var, when))
        line = PlotOverLine(Input=frames)
    else:
        cut = Slice(Input=frames)
        cut.SliceType = "Plane"
        cut.SliceType.Origin = mid
        cut.SliceType.Normal = [0, 0, 1]
        display = Show(cut, render)
        _colour(display, render, var, TASK["label"])
        _axes(display, TASK["x_label"], TASK["y_label"], TASK["z_label"])
        _oblique(render, cut, -25.0)
        middle = TASK["space_dims"][0]
        _title(render, "{{}}: {{}} at {{}} on the middle {{}} slice".format(TASK["name"], var, when, middle))
        line = PlotOverLine(Input=frames)
    line.Point1 = [b[0], mid[1], mid[2]]
    line.Point2 = [b[1], mid[1], mid[2]]
    where = "{{}}: along x through the middle, {{}}".format(TASK["name"], when)
    chart = _chart(TASK["x_label"], TASK["label"], where, b[:2])
    _lines(Show(line, chart), arrays, "Points_X")
    return render, chart


def series_views(args):
    var = TASK["variable"]
    curve = OpenDataFile(_file(TASK["vtp"]))
    curve.UpdatePipeline()
    if TASK["kind"] == "orbit":
        render = CreateView("RenderView")
        render.InteractionMode = "2D"
        display = Show(curve, render)
        _colour(display, render, "time", TASK["t_label"])
        display.LineWidth = 2.0
        if var + "_ref" in curve.PointData.keys():
            ref = Calculator(Input=curve)
            ref.CoordinateResults = 1
            ref.Function = "{{0}}_ref_X*iHat + {{0}}_ref_Y*jHat".format(var)
            ref.ResultArrayName = "reference_orbit"
            shown = Show(ref, render)
            ColorBy(shown, None)
            shown.AmbientColor = shown.DiffuseColor = [0.55, 0.55, 0.55]
            shown.LineWidth = 1.0
        _axes(display, TASK["c_labels"][0], TASK["c_labels"][1])
        _title(render, "{{}}: the orbit coloured by time; reference in grey".format(TASK["name"]))
        render.ResetCamera()
        return (render,)
    chart = _chart(TASK["t_label"], TASK["label"], TASK["name"], curve.PointData["time"].GetRange())
    arrays = [a for a in (var, var + "_ref") if a in curve.PointData.keys()]
    _lines(Show(curve, chart), arrays, "time")
    return (chart,)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--screenshot", metavar="PNG", help="save the views to this image and exit")
    parser.add_argument("--time", type=float, help="show the served slice nearest to this time")
    parser.add_argument("--nc", action="store_true", help="read the task file {name}.nc (netCDF CF reader)")
    parser.add_argument("--size", type=int, nargs=2, default=[1600, 700], metavar=("W", "H"))
    args, _ = parser.parse_known_args(sys.argv[1:] if argv is None and hasattr(sys, "argv") else argv or [])
    if args.screenshot and sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        print(
            "no X display: if ParaView crashes (SIGSEGV in XSync), run it under a virtual one: "
            "xvfb-run -a pvpython " + " ".join(sys.argv),
            file=sys.stderr,
        )
    if TASK["kind"] in ("series", "orbit"):
        if args.nc:
            sys.exit("--nc: 1D fields are shown from {{}}; drop --nc".format(TASK["vtp"]))
        views = series_views(args)
    else:
        views = lattice_views(args)
    views = [v for v in views if v is not None]
    layout = CreateLayout(TASK["name"])
    if len(views) == 2:
        layout.SplitHorizontal(0, 0.55)
        AssignViewToLayout(view=views[0], layout=layout, hint=1)
        AssignViewToLayout(view=views[1], layout=layout, hint=2)
    else:
        AssignViewToLayout(view=views[0], layout=layout, hint=0)
    for view in views:
        Render(view)
    if args.screenshot:
        layout.SetSize(*args.size)
        SaveScreenshot(args.screenshot, layout, SaveAllViews=1, ImageResolution=list(args.size))
        print("wrote " + args.screenshot)


main()
'''
