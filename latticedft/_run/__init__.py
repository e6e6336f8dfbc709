"""A case run: the stages the command line runs on a case, and the checks made before anything is written.

- ``_data``: a case's fields read and checked (:func:`check_case`) into :class:`CaseData`;
- ``_train``: its model learned (:func:`train_model`), chosen first with ``[model] select``;
- ``_task``: one task served, measured and logged (:func:`serve_task`) into a :class:`TaskOutcome`;
- ``_record``: what ``summary.json`` records of a task (:class:`TaskRecord`), and when its accuracy is warned of;
- ``_guards``: the checks made before anything is written (file-name limits, memory, the case's inputs);
- ``_charges``: the Noether charges of a task, checked against its lattice and measured along it;
- ``_calib``: the error bar's calibration law measured after training, and a served task's calibrated band;
- ``_meter``: a task's errors and invariant measured slice by slice as it is served with an output cadence.

Each stage logs INFO lines (to stderr via the command line) and DEBUG details (to ``results/run.log``).
"""

from __future__ import annotations

from ._calib import case_calibration as case_calibration
from ._data import CaseData as CaseData
from ._data import TaskData as TaskData
from ._data import check_case as check_case
from ._guards import case_inputs as case_inputs
from ._guards import check_before_writing as check_before_writing
from ._record import RELATIVE_ERROR_LIMIT as RELATIVE_ERROR_LIMIT
from ._record import TaskRecord as TaskRecord
from ._task import TaskOutcome as TaskOutcome
from ._task import serve_task as serve_task
from ._train import train_model as train_model

__all__ = [
    "RELATIVE_ERROR_LIMIT",
    "CaseData",
    "TaskData",
    "TaskOutcome",
    "TaskRecord",
    "case_calibration",
    "case_inputs",
    "check_before_writing",
    "check_case",
    "serve_task",
    "train_model",
]
