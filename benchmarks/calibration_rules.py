"""Calibration rules scored on recorded slices: would another law have met more rows of the calibration table?

    python -m benchmarks.calibration_rules FILE [FILE ...] [--rows] [--tests] [--moved]

Reads the JSON files written by ``python -m benchmarks.calibration --record FILE`` (each row's law, the trial's
held-out samples and, per test field, the per-slice error and every band). Every rule refits the law on the
recorded held-out samples exactly as :func:`latticedft._calibrate._fit` does, changed where the rule says, and forms
the bands as the benchmark does: the single band is the larger of the law (``A * scale * (k - 1)^exponent``, ``A``
the served field's largest magnitude) and the trial's recorded disagreement; an ensemble's band is its members'
spread times ``spread_scale`` floored at the trial's disagreement (``Calibration.band``; without a
``spread_scale``, the spread floored at the single band). The rule ``today`` is the code as it is: it must give
back every recorded band (the largest relative difference is printed, and a difference above ``1e-9`` stops the
script), so the other rules are scored on the same slices as the table. A row meets when one of its bands meets
both targets (2-sigma coverage 80-99 %, mean band over mean error 0.5-2), as in the calibration table.

Printed: per rule, the single bands and rows meeting, and the rows it gains and loses (with their bands);
``--moved``: every band that moved, from today's to the rule's. ``--rows``: the per-row table of ``today`` too.
``--tests``: per test field of every row, what tells why its band misses: its slices against the longest window
the law was measured on, its value range and amplitude (largest less smallest value) against the training
fields', how many of the calibration's warnings it drew, the share of its slices within twice the single band,
its error over the law and the trial's disagreement over its error (medians over its slices), the growth
exponent of its error (least squares of ``log error`` against ``log (k - 1)``) beside the law's, and the
candidates' ratio (:meth:`latticedft._calibrate.Calibration.candidates_ratio`: how much more the two best
candidates' trials disagree on it than on the training fields; ``warned`` when its warning fired; ``-`` without a
runner-up, or in a record made before it).
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from latticedft._calibration_law import EXPONENT_RANGE, QUANTILE

COVERAGE = (0.8, 0.99)
RATIO = (0.5, 2.0)
#: Largest relative difference allowed between a recorded band and the rule ``today``'s.
REPRODUCED = 1e-9


@dataclass
class Row:
    """One recorded row: its law (``Calibration.to_dict``), the trial's held-out samples and its test fields."""

    label: str
    noise: float
    law: dict[str, Any]
    held: list[dict[str, np.ndarray]]
    tests: list[dict[str, Any]]

    @property
    def name(self) -> str:
        return f"{self.label} (noise {self.noise:g})"


@dataclass
class Law:
    """A refitted law: its scale and exponent, and what a rule changes past the longest window."""

    scale: float
    exponent: float
    #: The exponent past the longest window (None: the same as before it).
    beyond: float | None = None
    #: Per test field, a factor on the law (None: 1).
    factor: Callable[[Row, dict[str, Any]], float] | None = None


@dataclass
class Rule:
    """A law and band rule: how the exponent and scale are fitted, and how the bands are formed."""

    name: str
    exponent_of: str = "target"  # "target" (the trial's error or the runner-up's disagreement) or "rel"
    held_only: bool = False  # the exponent fitted on the held-out slices only
    quantile: float = QUANTILE
    beyond: Callable[[float], float] | None = None  # the exponent past the longest window, from the fitted one
    factor: Callable[[Row, dict[str, Any]], float] | None = None
    ensemble: str = "today"  # "today", "widened" (at least the single band), "sharper" (law or spread)
    #: The exponent's least squares with every slice weighted by ``1/k`` (each factor of time counting the same).
    per_decade: bool = False
    #: The finite-sample conformal level ``ceil((n + 1) q) / n`` of ``n`` held-out slices instead of ``q``.
    conformal: bool = False
    #: The scale from the mean of the held-out ``r(k) / (k - 1)^exponent`` instead of its quantile (halved).
    mean_scale: bool = False
    #: A factor on the trial's disagreement on the task.
    trial_factor: float = 1.0
    #: Past the longest window, the single band is the trial's disagreement alone (the law not extrapolated).
    trial_alone_past: bool = False


def read(paths: list[str]) -> list[Row]:
    """The rows of every record file, in order."""
    rows = []
    for p in paths:
        try:
            data = json.loads(Path(p).read_text())
        except (OSError, ValueError) as err:
            raise SystemExit(f"{p}: not a record of `python -m benchmarks.calibration --record` ({err})") from None
        for r in data:
            held = [{k: np.asarray(v, dtype=np.float64) for k, v in s.items() if k != "field"} for s in r["held_out"]]
            for s in held:
                s["held"] = s["held"].astype(bool)
            tests = [
                {
                    k: (np.asarray(v, dtype=np.float64) if isinstance(v, list) and k != "warnings" else v)
                    for k, v in t.items()
                }
                for t in r["tests"]
            ]
            rows.append(Row(r["row"], float(r["noise"]), r["law"], held, tests))
    return rows


def refit(row: Row, rule: Rule) -> Law:
    """The law of ``row`` refitted on its held-out samples as :func:`latticedft._calibrate._fit` fits it, with the
    rule's changes."""
    origin = float(row.law.get("origin", 0.0))
    pick = (lambda s: s["held"]) if rule.held_only else (lambda s: np.ones(s["k"].shape, dtype=bool))
    k_all = np.concatenate([s["k"][pick(s)] for s in row.held]) if row.held else np.zeros(0)
    y_all = np.concatenate([s[rule.exponent_of][pick(s)] for s in row.held]) if row.held else np.zeros(0)
    ok = np.isfinite(y_all) & (y_all > 0)
    p = 0.0
    if np.unique(k_all[ok]).size >= 2:
        w = 1 / np.sqrt(k_all[ok] - origin) if rule.per_decade else None
        p = float(np.polyfit(np.log(k_all[ok] - origin), np.log(y_all[ok]), 1, w=w)[0])
    p = float(np.clip(p, *EXPONENT_RANGE))
    k = np.concatenate([s["k"][s["held"]] for s in row.held]) if row.held else np.zeros(0)
    r = np.concatenate([s["rel"][s["held"]] for s in row.held]) if row.held else np.zeros(0)
    z = np.where(np.isfinite(r), r, np.inf) / (k - origin) ** p
    level = min(math.ceil((z.size + 1) * rule.quantile) / z.size, 1.0) if rule.conformal and z.size else rule.quantile
    q = float(np.quantile(z, level, method="higher")) if z.size else math.inf
    if not math.isfinite(q) and np.isfinite(z).any():
        q = float(np.quantile(z[np.isfinite(z)], level, method="higher"))
    if rule.mean_scale and np.isfinite(z).any():
        q = 2 * float(np.mean(z[np.isfinite(z)]))
    scale = q / 2
    scale = scale if math.isfinite(scale) and scale > 0 else float(np.finfo(float).tiny)
    return Law(scale, p, None if rule.beyond is None else rule.beyond(p), rule.factor)


def law_band(row: Row, law: Law, test: dict[str, Any]) -> np.ndarray:
    """The law on a test field's recorded slices (``k >= 2``), as ``Calibration.estimate`` gives it."""
    origin = float(row.law.get("origin", 0.0))
    k = np.arange(2, int(test["slices"]), dtype=np.float64)
    t = np.maximum(k - origin, 1.0)
    est = float(test["amplitude"]) * law.scale * t**law.exponent
    if law.beyond is not None:
        w = max(float(row.law["slices"]) - 1 - origin, 1.0)  # the last slice of the longest window, in steps
        past = t > w
        est = np.where(past, float(test["amplitude"]) * law.scale * w**law.exponent * (t / w) ** law.beyond, est)
    if law.factor is not None:
        est = est * law.factor(row, test)
    return est


def bands(row: Row, rule: Rule) -> list[dict[str, np.ndarray]]:
    """Per test field, its single band and (with an ensemble) its ensemble band under ``rule``."""
    law = refit(row, rule)
    spread_scale = row.law.get("spread_scale")
    out = []
    for t in row.tests:
        trial = np.asarray(t["trial"], dtype=np.float64) * rule.trial_factor
        single = np.fmax(law_band(row, law, t), trial)
        if rule.trial_alone_past:
            steps = np.arange(2, int(t["slices"]), dtype=np.float64) - float(row.law.get("origin", 0.0))
            single = np.where(steps > float(row.law["slices"]) - 1 - float(row.law.get("origin", 0.0)), trial, single)
        b = {"single": single}
        if "raw" in t and "ensemble" in t:
            raw = np.asarray(t["raw"], dtype=np.float64)
            if spread_scale is None:
                ens = np.where(raw > 0, np.fmax(raw, single), single)
            else:
                floor = np.nan_to_num(trial)
                s = raw * float(spread_scale)
                ens = np.where(s > 0, np.fmax(s, floor), floor)
            if rule.ensemble == "widened":
                ens = np.fmax(ens, single)
            elif rule.ensemble == "sharper":
                sharper_spread = (row.law.get("spread_std_over_error") or math.inf) < row.law["std_over_error"]
                ens = ens if sharper_spread or spread_scale is None else single
            b["ensemble"] = ens
        out.append(b)
    return out


def score(row: Row, per_test: list[dict[str, np.ndarray]], name: str) -> tuple[float, float] | None:
    """Coverage (share of slices whose error is within twice the band) and mean band over mean error, pooled over
    the row's test fields as the benchmark pools them (None when the row has no such band)."""
    if not per_test or any(name not in b for b in per_test):
        return None
    e = np.concatenate([np.asarray(t["error"], dtype=np.float64) for t in row.tests])
    b = np.concatenate([bb[name] for bb in per_test])
    ok = np.isfinite(e)
    b = np.where(np.isfinite(b), b, 0.0)
    return float(np.mean(e[ok] <= 2 * b[ok])), float(b[ok].mean() / max(e[ok].mean(), 1e-300))


def meets(s: tuple[float, float] | None) -> bool:
    return s is not None and COVERAGE[0] <= s[0] <= COVERAGE[1] and RATIO[0] <= s[1] <= RATIO[1]


def reproduced(rows: list[Row]) -> float:
    """The largest relative difference between a recorded law (scale, exponent) or band (single, ensemble) and the
    rule ``today``'s."""
    worst = 0.0
    for row in rows:
        law = refit(row, RULES[0])
        for fitted, recorded in ((law.scale, row.law["scale"]), (law.exponent, row.law["exponent"])):
            worst = max(worst, abs(fitted - recorded) / max(abs(recorded), 1e-300) if fitted != recorded else 0.0)
        for t, b in zip(row.tests, bands(row, RULES[0]), strict=True):
            for name in ("single", "ensemble"):
                if name not in b or name not in t:
                    continue
                mine, theirs = b[name], np.asarray(t[name], dtype=np.float64)
                both = np.isfinite(theirs) & np.isfinite(mine)
                if not np.array_equal(np.isfinite(theirs), np.isfinite(mine)):
                    return math.inf
                d = np.abs(mine[both] - theirs[both]) / np.maximum(np.abs(theirs[both]), 1e-300)
                worst = max(worst, float(d.max()) if d.size else 0.0)
    return worst


def _span_ratio(row: Row, test: dict[str, Any]) -> float:
    """How far the served amplitude (range of values) lies outside the training fields' amplitudes, as a ratio
    (1 inside them)."""
    lo, hi = row.law.get("span_low"), row.law.get("span_high")
    span = float(test["high"]) - float(test["low"])
    if lo is None or hi is None or not span > 0:
        return 1.0
    return max(span / hi, lo / span, 1.0)


def _range_excess(row: Row, test: dict[str, Any]) -> float:
    """``1 + d``: ``d`` how far the served field leaves the training fields' value range, over its width."""
    width = max(float(row.law["high"]) - float(row.law["low"]), 1e-300)
    d = max(float(row.law["low"]) - float(test["low"]), float(test["high"]) - float(row.law["high"]), 0.0)
    return 1.0 + d / width


RULES: list[Rule] = [
    Rule("today"),
    Rule("growth linear past the longest window", beyond=lambda p: 1.0),
    Rule("exponent capped at 1 past the longest window", beyond=lambda p: min(p, 1.0)),
    Rule("exponent at least 1 past the longest window", beyond=lambda p: max(p, 1.0)),
    Rule("exponent fitted to the trial's own error", exponent_of="rel"),
    Rule("exponent fitted on the held-out slices only", held_only=True),
    Rule("law x amplitude ratio outside the training amplitudes", factor=_span_ratio),
    Rule("law x amplitude ratio squared", factor=lambda r, t: _span_ratio(r, t) ** 2),
    Rule("law x (1 + d), d: distance outside the value range", factor=_range_excess),
    Rule("law x (1 + d)^2", factor=lambda r, t: _range_excess(r, t) ** 2),
    Rule("exponent fitted with every slice weighted by 1/k", per_decade=True),
    Rule("finite-sample conformal quantile, ceil((n + 1) 0.95) / n", conformal=True),
    Rule("scale from the mean held-out error", mean_scale=True),
    Rule("scale from the 90 % quantile", quantile=0.90),
    Rule("scale from the 85 % quantile", quantile=0.85),
    Rule("scale from the 80 % quantile", quantile=0.80),
    Rule("trial's disagreement scaled by 1 / sqrt(1 + 1/0.7)", trial_factor=1 / math.sqrt(1 + 1 / 0.7)),
    Rule("the trial's disagreement alone past the longest window", trial_alone_past=True),
    Rule("ensemble: spread widened to the single band", ensemble="widened"),
    Rule("ensemble: the sharper of law and spread on the held-out slices", ensemble="sharper"),
]


def _fmt(s: tuple[float, float] | None) -> str:
    return "-" if s is None else f"{100 * s[0]:.3g} %, {s[1]:.3g}"


def facts(row: Row) -> list[list[Any]]:
    """Per test field of ``row``: the columns ``--tests`` prints (see the module docstring)."""
    law, out = refit(row, RULES[0]), []
    for i, (t, b) in enumerate(zip(row.tests, bands(row, RULES[0]), strict=True)):
        e = np.asarray(t["error"], dtype=np.float64)
        lb = law_band(row, law, t)
        ok = np.isfinite(e) & (e > 0)
        k = np.arange(2, 2 + e.size, dtype=np.float64) - float(row.law.get("origin", 0.0))
        grow = float(np.polyfit(np.log(np.maximum(k[ok], 1.0)), np.log(e[ok]), 1)[0]) if ok.sum() >= 2 else math.nan
        with np.errstate(divide="ignore", invalid="ignore"):
            over_law = float(np.nanmedian(e / lb)) if e.size else math.nan
            trial = float(np.nanmedian(np.asarray(t["trial"], dtype=np.float64) / e)) if e.size else math.nan
        span = float(t["high"]) - float(t["low"])
        lo, hi = row.law.get("span_low"), row.law.get("span_high")
        out.append(
            [
                i,
                f"{int(t['slices'])} ({int(row.law['slices'])})",
                f"[{float(t['low']):.3g}, {float(t['high']):.3g}] ([{row.law['low']:.3g}, {row.law['high']:.3g}])",
                f"{span:.3g}" + ("" if lo is None or hi is None else f" ([{lo:.3g}, {hi:.3g}])"),
                len(t.get("warnings") or []),
                f"{100 * float(np.mean(e[np.isfinite(e)] <= 2 * np.nan_to_num(b['single'])[np.isfinite(e)])):.3g} %",
                f"{over_law:.3g}",
                f"{trial:.3g}",
                f"{grow:.2f} ({law.exponent:.2f})",
                _candidates(t),
            ]
        )
    return out


def _candidates(test: dict[str, Any]) -> str:
    """The ``candidates`` column of ``--tests``: the test's recorded candidates' ratio, and whether it warned."""
    ratio = test.get("candidates_ratio")
    if ratio is None:
        return "-"
    warned = any("the two best candidates" in w for w in test.get("warnings") or [])
    return f"{ratio:.3g}" + (" (warned)" if warned else "")


def main(argv: list[str]) -> int:
    paths = [a for a in argv if not a.startswith("--")]
    if not paths:
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 2
    rows = read(paths)
    diff = reproduced(rows)
    print(f"# {len(rows)} rows; largest relative difference of the rule `today` from the recorded bands: {diff:.2e}")
    if not diff <= REPRODUCED:
        print(
            f"the rule `today` does not give back the recorded bands (above {REPRODUCED:g}): the records are of "
            "another law",
            file=sys.stderr,
        )
        return 1
    base = {row.name: [score(row, bands(row, RULES[0]), n) for n in ("single", "ensemble")] for row in rows}
    if "--rows" in argv:
        print("\n| row | single | ensemble |\n|---|---|---|")
        for row in rows:
            s, e = base[row.name]
            tag = {True: " (meets)", False: ""}
            print(f"| {row.name} | {_fmt(s)}{tag[meets(s)]} | {_fmt(e)}{tag[meets(e)]} |")
    if "--tests" in argv:
        head = (
            "test | slices (windows) | values (training) | amplitude (training) | warnings | covered | error / law "
            "| trial / error | error growth (law) | candidates"
        )
        for row in rows:
            print(f"\n{row.name}\n\n| {head} |\n|{'---|' * (head.count('|') + 1)}")
            for f in facts(row):
                print("| " + " | ".join(str(c) for c in f) + " |")
    print("\n| rule | single bands meeting | rows meeting | rows gained | rows lost |\n|---|---|---|---|---|")
    moved = []
    for rule in RULES:
        n_single, gained, lost = 0, [], []
        n_rows = 0
        for row in rows:
            new = [score(row, bands(row, rule), n) for n in ("single", "ensemble")]
            old = base[row.name]
            n_single += meets(new[0])
            n_rows += meets(new[0]) or meets(new[1])
            was, now = meets(old[0]) or meets(old[1]), meets(new[0]) or meets(new[1])
            band = ", ".join(f"{n} {_fmt(b)}" for n, b in zip(("single", "ensemble"), new, strict=True) if b)
            if now and not was:
                gained.append(f"{row.name} ({band})")
            elif was and not now:
                lost.append(f"{row.name} ({band})")
            for name, a, b in zip(("single", "ensemble"), old, new, strict=True):
                if a is not None and b is not None and _fmt(a) != _fmt(b):
                    moved.append(f"- {rule.name}: {row.name}, {name} {_fmt(a)} -> {_fmt(b)}")
        print(f"| {rule.name} | {n_single} | {n_rows} | {'; '.join(gained) or '-'} | {'; '.join(lost) or '-'} |")
    if "--moved" in argv:
        print("\nEvery band that moved (coverage, std/error: today -> the rule):\n")
        print("\n".join(moved))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
