"""The withheld-effect benchmark: generated cases diagnosed blind with one fixed setting, scored against the truth."""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from grounder.diagnosis.cases import ALL_CASES, MULTI_BODY_SCENARIOS, CaseSpec, make_case
from grounder.diagnosis.pipeline import DiagnoseOptions, diagnose
from grounder.errors import GrounderError, integer_in
from image2sim_common.outdir import write_text_atomic
from image2sim_common.progress import ProgressFn

MEASUREMENT_EFFECTS = ("length_scale", "time_scale", "velocity_lag")
UNEXPLAINED_THRESHOLD = 0.5
"""An out-of-library case counts as reported "largely unexplained" when more than this fraction of its held-out gap
remains."""
MIN_TRAJECTORIES = 8
"""Fewest trajectories per case: the diagnosis holds 30% of them out for its check."""
MAX_TRAJECTORIES = 1000
"""Most trajectories per case. Each is simulated (1 s at 2 ms steps) and then re-simulated for every candidate effect
and fitted value: ~0.7 s of diagnosis per trajectory per case on 2 threads, so 1000 take ~12 min a case and ~3 h for
the 16 cases (the default 16 take seconds)."""


def check_num_trajectories(num_trajectories: int) -> None:
    """Raises GrounderError unless `num_trajectories` is an integer in [MIN_TRAJECTORIES, MAX_TRAJECTORIES]."""
    if not integer_in(num_trajectories, MIN_TRAJECTORIES, MAX_TRAJECTORIES):
        raise GrounderError(
            f"num_trajectories={num_trajectories!r} but expected an integer between {MIN_TRAJECTORIES} and "
            f"{MAX_TRAJECTORIES} per case"
        )


@dataclass(frozen=True, kw_only=True)
class BenchResult:
    """One diagnosed case."""

    case: str
    hidden: tuple[str, ...]
    true_values: dict[str, dict[str, float]]
    in_library: bool
    top1: str
    top1_params: dict[str, float]
    selected: tuple[str, ...]
    gap_before: float
    gap_after: float
    reduction: float
    unexplained_fraction: float
    reduction_above_noise: float
    noise_floor: float
    seconds: float
    top1_target: str = ""  # "" = all bodies; a body; or a contact pair "a|b"
    hidden_targets: dict[str, str] = field(default_factory=dict)
    contact_pairs: tuple[str, ...] = ()
    bodies: tuple[str, ...] = ()
    unexplained_by_body: dict[str, float] = field(default_factory=dict)
    multi_object: bool = False  # one of the multi-object cases (`cases.MULTI_BODY`)

    @property
    def no_gap(self) -> bool:
        return not self.hidden

    @property
    def place_correct(self) -> bool:
        """The top-ranked effect acts where the hidden one does (see `same_place`)."""
        if self.no_gap or not self.in_library or self.top1 not in self.hidden:
            return False
        return same_place(self.hidden_targets.get(self.top1, ""), self.top1_target, self.contact_pairs)

    @property
    def fit_error(self) -> float:
        """Largest relative error of the top-ranked effect's fitted values against the hidden ones (nan unless that
        effect is hidden); offsets whose true value is zero count against the largest true offset."""
        if self.top1 not in self.true_values:
            return float("nan")
        true = self.true_values[self.top1]
        scale = max(abs(v) for v in true.values()) or 1.0
        return max(abs(self.top1_params[k] - v) / (abs(v) if v else scale) for k, v in true.items())

    @property
    def correct(self) -> bool:
        """In-library: the top-ranked effect is a hidden one, at the hidden one's body or contact pair. No gap:
        nothing selected. Out-of-library: reported largely unexplained (on the body it acts on, if one)."""
        if self.no_gap:
            return not self.selected
        if self.in_library:
            return self.top1 in self.hidden and self.place_correct
        body = next(iter(self.hidden_targets.values()), "")
        if body:
            return self.unexplained_by_body.get(body, 0.0) > UNEXPLAINED_THRESHOLD
        return self.unexplained_fraction > UNEXPLAINED_THRESHOLD

    def to_json(self) -> dict[str, Any]:
        return {
            "case": self.case,
            "hidden": list(self.hidden),
            "true_values": self.true_values,
            "in_library": self.in_library,
            "top1": self.top1,
            "top1_params": self.top1_params,
            "selected": list(self.selected),
            "heldout_gap_before": self.gap_before,
            "heldout_gap_after": self.gap_after,
            "heldout_reduction": self.reduction,
            "unexplained_fraction": self.unexplained_fraction,
            "reduction_above_noise": self.reduction_above_noise,
            "noise_floor": self.noise_floor,
            "correct": self.correct,
            "seconds": self.seconds,
            "top1_target": self.top1_target or "all",
            "hidden_targets": {k: v or "all" for k, v in self.hidden_targets.items()},
            "place_correct": self.place_correct,
            "fit_error": None if np.isnan(self.fit_error) else self.fit_error,
            "contact_pairs": list(self.contact_pairs),
            "unexplained_by_body": self.unexplained_by_body,
            "multi_object": self.multi_object,
        }


def same_place(truth: str, named: str, contact_pairs: Sequence[str]) -> bool:
    """Whether an effect named at ``named`` acts where one at ``truth`` does ("" = everywhere). A body and a contact
    pair are the same place when that pair is the body's only contact in the recordings (a box that only ever
    touched the table): no data can tell them apart."""
    if truth == named:
        return True
    if not truth or not named:
        return False

    def only_pair(body: str) -> list[str]:
        return [p for p in contact_pairs if body in p.split("|")]

    if "|" in named and "|" not in truth:
        return only_pair(truth) == [named]
    if "|" in truth and "|" not in named:
        return only_pair(named) == [truth]
    return False


def run_case(
    spec: CaseSpec, num_trajectories: int = 16, nthread: int = 2, seed: int = 0, options: DiagnoseOptions | None = None
) -> BenchResult:
    """Generates one case and diagnoses it blind (``options`` default: the one benchmark setting)."""
    check_num_trajectories(num_trajectories)
    case = make_case(spec, num_trajectories, seed=seed)
    model = mujoco.MjModel.from_xml_string(case.scene_xml)
    t0 = time.perf_counter()
    diag = diagnose(
        model,
        case.trajectories,
        options or DiagnoseOptions(nthread=nthread),
        spec=mujoco.MjSpec.from_string(case.scene_xml),
    )
    seconds = time.perf_counter() - t0
    top = diag.effects[0]
    layout = diag.layout
    return BenchResult(
        case=spec.name,
        hidden=tuple(h.name for h in spec.hidden),
        true_values={h.name: h.values for h in spec.hidden},
        in_library=case.in_library,
        hidden_targets={h.name: h.target for h in spec.hidden},
        top1_target="" if top.target.kind == "all" else top.target.label,
        contact_pairs=tuple("|".join(p) for p in layout.pairs) if layout else (),
        bodies=layout.bodies if layout else (),
        unexplained_by_body={b: v["unexplained_fraction"] for b, v in diag.unexplained_by_body.items()},
        multi_object=spec.scenario in MULTI_BODY_SCENARIOS,
        top1=top.effect,
        top1_params=top.params,
        selected=tuple(diag.selected),
        gap_before=diag.heldout["gap_before"],
        gap_after=diag.heldout["gap_after"],
        reduction=diag.heldout["reduction"],
        unexplained_fraction=diag.unexplained_fraction,
        reduction_above_noise=diag.heldout["reduction_above_noise"],
        noise_floor=diag.heldout["noise_floor"],
        seconds=seconds,
    )


def select_cases(names: Sequence[str] | None) -> list[CaseSpec]:
    if not names:
        return list(ALL_CASES)
    known = {c.name: c for c in ALL_CASES}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise GrounderError(f"unknown case(s) {unknown}; available: {', '.join(known)}")
    return [known[n] for n in names]


def run_benchmark(
    names: Sequence[str] | None = None,
    num_trajectories: int = 16,
    nthread: int = 2,
    seed: int = 0,
    progress: ProgressFn | None = None,
) -> list[BenchResult]:
    """Runs the named cases (all by default) one after another; `progress(stage, done, total)` after each."""
    check_num_trajectories(num_trajectories)  # before the first case, not after it
    report = progress or (lambda _s, _d, _t: None)
    specs = select_cases(names)
    results = []
    for k, spec in enumerate(specs):
        report(f"withheld-effect cases ({spec.name})", k, len(specs))
        results.append(run_case(spec, num_trajectories, nthread, seed))
    report("withheld-effect cases", len(specs), len(specs))
    return results


def check_results_file(path: Path) -> None:
    """Refuses, before the benchmark's minutes, a results file that exists or whose folder cannot take it.

    Raises:
        GrounderError: `path` exists; its folder is a file, is missing, or cannot be written in.
    """
    if path.exists():
        raise GrounderError(f"--json {path} already exists; remove it or choose another file")
    folder = path.parent
    if folder.exists() and not folder.is_dir():
        raise GrounderError(f"--json {path}: {folder} is a file, not a folder; choose another place for the results")
    if not folder.is_dir():
        raise GrounderError(f"--json {path}: folder {folder} does not exist; create it or choose another file")
    try:  # an unwritable place (permissions, a read-only disk) is found now, not after the benchmark
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{path.name}.", suffix=".probe"):
            pass
    except OSError as exc:
        raise GrounderError(
            f"--json {path}: cannot write in {folder} ({exc.strerror}); choose a folder you can write to"
        ) from exc


def write_results(path: Path, results: Sequence[BenchResult]) -> None:
    """The results as a JSON list (`BenchResult.to_json` each), written whole or not at all."""
    write_text_atomic(path, json.dumps([r.to_json() for r in results], indent=2))


def _multi_summary(multi: Sequence[BenchResult]) -> list[str]:
    """Summary lines of the multi-object cases (issue 64's acceptance figures)."""
    if not multi:
        return []
    lines = []
    effect_cases = [r for r in multi if r.in_library and not r.no_gap]
    if effect_cases:
        n_ok = sum(r.correct for r in effect_cases)
        above = sorted(r.reduction_above_noise for r in effect_cases)
        errors = [r.fit_error for r in effect_cases if not np.isnan(r.fit_error)]
        lines.append(
            f"multi-object in-library cases: effect and body/pair named {n_ok}/{len(effect_cases)} "
            f"({n_ok / len(effect_cases):.0%}); held-out reduction above the noise floor min {above[0]:.0%}, median "
            f"{above[len(above) // 2]:.0%}; fitted values off by at most {max(errors, default=float('nan')):.1%}; "
            f"time per case max {max(r.seconds for r in multi):.0f} s "
            f"(up to {max(len(r.bodies) for r in multi)} bodies)"
        )
    for r in multi:
        if r.no_gap:
            lines.append(
                f"no-gap {r.case}: selected {', '.join(r.selected) or 'nothing'} -> {'ok' if r.correct else 'WRONG'}"
            )
        elif not r.in_library:
            body = next(iter(r.hidden_targets.values()), "")
            lines.append(
                f"out-of-library {r.case}: unexplained on {body or 'all'} "
                f"{r.unexplained_by_body.get(body, r.unexplained_fraction):.0%} -> "
                f"{'reported largely unexplained' if r.correct else 'NOT reported as unexplained'}"
            )
    return lines


def _cell(text: str) -> str:
    """Table cell text: a contact pair's "a|b" would end a markdown cell."""
    return text.replace("|", "\\|")


def _fmt_params(values: dict[str, float]) -> str:
    return ", ".join(f"{k}={v:.3g}" for k, v in values.items())


def format_table(results: Sequence[BenchResult]) -> str:
    """A markdown table per case, the summary figures and the confusion matrix (true effect x selected first)."""
    lines = [
        "| case | hidden (true values) | top-1 (fitted) | selected | held-out gap before -> after | reduction "
        "| above noise | verdict | s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        hidden = (
            "; ".join(
                f"{h}{'@' + r.hidden_targets[h] if r.hidden_targets.get(h) else ''} ({_fmt_params(r.true_values[h])})"
                for h in r.hidden
            )
            or "none"
        )
        mark = "ok" if r.correct else "WRONG"
        top = r.top1 + (f"@{r.top1_target}" if r.top1_target else "")
        lines.append(
            f"| {_cell(r.case)} | {_cell(hidden)} | {_cell(top)} ({_fmt_params(r.top1_params)}) "
            f"| {_cell(', '.join(r.selected) or 'none')} | {r.gap_before:.4f} -> {r.gap_after:.4f} "
            f"| {r.reduction:.0%} | {r.reduction_above_noise:.0%} | {mark} | {r.seconds:.0f} |"
        )
    one_body = [r for r in results if not r.multi_object]
    multi = [r for r in results if r.multi_object]
    single = [r for r in one_body if r.in_library and len(r.hidden) == 1]
    outside = [r for r in one_body if not r.in_library]
    lines.append("")
    for label, group in (
        ("in-library single-effect cases", single),
        ("  of which physical effects", [r for r in single if r.hidden[0] not in MEASUREMENT_EFFECTS]),
        ("  of which measurement biases", [r for r in single if r.hidden[0] in MEASUREMENT_EFFECTS]),
        ("multi-effect cases", [r for r in one_body if r.in_library and len(r.hidden) > 1]),
    ):
        if not group:
            continue
        n_ok = sum(r.correct for r in group)
        reds = sorted(r.reduction for r in group)
        above = sorted(r.reduction_above_noise for r in group)
        lines.append(
            f"{label}: top-1 correct {n_ok}/{len(group)} ({n_ok / len(group):.0%}); held-out reduction min "
            f"{reds[0]:.0%}, median {reds[len(reds) // 2]:.0%}; above the noise floor min {above[0]:.0%}, "
            f"median {above[len(above) // 2]:.0%}; time per case max {max(r.seconds for r in group):.0f} s"
        )
    for r in outside:
        lines.append(
            f"out-of-library {r.case}: unexplained fraction {r.unexplained_fraction:.0%} -> "
            f"{'reported largely unexplained' if r.correct else 'NOT reported as unexplained'}"
        )
    lines += _multi_summary(multi)
    # Confusion matrix: true (first hidden effect, or the out-of-library name) x first selected ("none" if none).
    truths = list(dict.fromkeys("+".join(r.hidden) or "none" for r in results))
    preds = list(dict.fromkeys([*(r.selected[0] if r.selected else "none" for r in results)]))
    lines.append("")
    lines.append("confusion matrix (rows: hidden effect(s); columns: first selected effect)")
    lines.append("| hidden \\ selected | " + " | ".join(_cell(p) for p in preds) + " |")
    lines.append("|---|" + "---|" * len(preds))
    for t in truths:
        counts = [
            sum(
                1
                for r in results
                if ("+".join(r.hidden) or "none") == t and (r.selected[0] if r.selected else "none") == p
            )
            for p in preds
        ]
        lines.append(f"| {t} | " + " | ".join(str(c) if c else "." for c in counts) + " |")
    return "\n".join(lines)
