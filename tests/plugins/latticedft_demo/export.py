"""An export format from outside latticedft: the served field as a plain text table."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from latticedft.io.exporters import Exporter, ExportTask


class TableExporter(Exporter):
    """``<task>.demo.txt``: one row per time slice, its time then the field's values."""

    name = "demo-table"
    summary = "the served field as a text table, one row per slice"
    files = ("{name}.demo.txt",)

    def write(self, task: ExportTask) -> list[Path]:
        field = task.field
        time = np.asarray(field[field.dims[0]].values, dtype=float)
        values = np.asarray(field.values, dtype=float).reshape(len(time), -1)
        path = task.folder / f"{task.name}.demo.txt"
        np.savetxt(path, np.column_stack([time, values]), header=f"{task.variable} by slice ({self.name})")
        return [path]
