"""A calibrated parameter's entry in the report (`interaction.json`, `calibration.parameters`) and an object's
calibration status: `prior_record` (the prior stands), `fitted_record` (after a fit that gives a best value and the
range the clip cannot tell apart) and `fit_status`. Shared by the windowed, the multiple-shooting and the impacts
calibrations.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any


def prior_record(p: Any) -> dict[str, Any]:
    """A parameter's report entry when the prior stands: value = nominal, interval = bounds, unconstrained."""
    bounds = [p.lower, p.upper]
    return {
        "nominal": p.nominal,
        "value": p.nominal,
        "interval": bounds,
        "bounds": list(bounds),
        "unit": p.unit,
        "constrained": False,
    }


def fitted_record(parameter: Any, value: float, span: Sequence[float], resolved: bool) -> dict[str, Any]:
    """A parameter's report entry after a fit that gives a best value and the range the clip cannot tell apart
    (`indistinguishable`): calibrated to the value where `resolved`, else the prior with the fit as `unresolved_fit`.
    Shared by the multiple-shooting and the impacts calibrations."""
    record = prior_record(parameter)
    record["indistinguishable"] = [float(v) for v in span]
    if resolved:
        record.update(value=float(value), interval=[float(v) for v in span], constrained=True)
    else:
        record["unresolved_fit"] = float(value)
    return record


def fit_status(searched: str, records: Mapping[str, Mapping[str, Any]]) -> str:
    """One object's calibration status after such a fit: what was searched (`searched`, a phrase) and which values
    it left at the prior."""
    kept = [n for n, r in records.items() if not r["constrained"]]
    if len(kept) == len(records):
        return f"not calibrated: {searched} resolved none of its values; prior kept"
    return f"calibrated by {searched}" + (f"; not resolved by the clip, prior kept: {kept}" if kept else "")
