"""``latticedft info CASE``: print the case and, when results/ holds one, the learned model and its summary."""

from __future__ import annotations

import argparse
import json
import logging

from ._common import OK, add_case_arguments, open_case, results_dir

log = logging.getLogger("latticedft")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="print the case and the learned model (if any)", description=__doc__)
    add_case_arguments(p)
    p.add_argument("--all", action="store_true", help="every term of the learned L_d (default: the 12 largest)")


def _fmt(v: object) -> str:
    return f"{v:.3e}" if isinstance(v, float) else str(v)


def main(args: argparse.Namespace, argv: list[str]) -> int:
    from .._learn._report import fit_verdict, symmetry_lines
    from .._results import load_verified_model, read_summary

    case = open_case(args)
    print(f"case {case.name} ({case.root})")
    opts = ", ".join(f"{k}={v!r}" for k, v in case.model.options.items())
    print(f"  model: {case.model.kind}({opts})" + (f", stencil {case.model.stencil}" if case.model.stencil else ""))
    print(f"  train: {', '.join(case.train.patterns)} -> {len(case.train.data)} file(s)")
    for t in case.serve:
        print(f"  serve {t.name}: from {t.source.name}, slices {t.slices or 'all'}, mode {t.options.mode}")
    if case.overrides:
        print(f"  overrides: {', '.join(case.overrides)}")
    dest = results_dir(args, case)
    if not (dest / "model.pt").is_file():
        print(f"no learned model in {dest}")
        return OK
    model = load_verified_model(dest)
    print(f"learned model ({dest / 'model.pt'}):")
    print(model.describe(max_terms=None if args.all else 12))
    summary = read_summary(dest)
    if summary:
        train = summary.get("train") or {}
        keys = (
            "loss",
            "rel_res",
            "iterations",
            "wall_time",
            "gauge",
            "gauge_residual",
            "hessian_min_sv",
            "hessian_cond",
        )
        print("training: " + ", ".join(f"{k} {_fmt(train[k])}" for k in keys if k in train))
        if isinstance(train.get("rel_res"), float):
            print(fit_verdict(bool(train.get("degenerate")), train["rel_res"], str(train.get("method", "exact"))))
        if isinstance(train.get("symmetries"), list):
            print("symmetries of the learned L_d over the training data:")
            for line in symmetry_lines(train["symmetries"]):
                print(f"  {line}")
        for name, t in (summary.get("tasks") or {}).items():
            parts = [("complete" if t.get("complete") else "INCOMPLETE"), f"{t.get('slices')} slices"]
            for k in (
                "max_error",
                "rms_error",
                "newton_iterations",
                "wall_time",
                "sites_per_second",
                "invariant_drift",
            ):
                if t.get(k) is not None:
                    parts.append(f"{k} {_fmt(t[k])}")
            if t.get("baseline"):
                parts.append(f"baseline max_error {_fmt(t['baseline'].get('max_error_same_slices'))}")
            for charge, c in (t.get("charges") or {}).items():
                parts.append(f"{charge} drift {_fmt(c.get('relative_drift'))}")
            print(f"task {name}: " + ", ".join(parts))
        print(
            f"exit status of the last run: {summary.get('exit_status')}; versions "
            f"{json.dumps(summary.get('versions', {}))}"
        )
    return OK
