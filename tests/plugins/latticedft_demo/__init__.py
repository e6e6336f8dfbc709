"""A package that extends latticedft from outside: one model kind and one export format.

Its ``latticedft_demo-0.1.dist-info/entry_points.txt`` (beside this folder) declares them, as an installed
package's ``pyproject.toml`` would::

    [project.entry-points."latticedft.models"]
    demo-well = "latticedft_demo.models:DemoWell"

    [project.entry-points."latticedft.exporters"]
    demo-table = "latticedft_demo.export:TableExporter"

The tests put this folder on ``sys.path``; nothing is installed.
"""
