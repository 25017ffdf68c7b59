"""The evaluation stage's result: the paper's model for coarse, fine and ICP of one pair side by side."""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from ..fine.fitting import CylinderFit
from ..params import EvaluationParams
from ..results import Metric
from ..scan import Scan
from .branches import EvaluationResult, evaluate_pair, find_branches, reference_layers
from .icp import IcpResult


@dataclass(frozen=True, kw_only=True)
class PairReport:
    """Evaluation of one target: its coarse, fine and (when it ran) ICP transforms.

    Each is an `EvaluationResult`: the paper's branch-centre error (eq. 8) and, when the truth is
    known, the rotation error and the mean displacement of the target's points.
    """

    ok: bool
    message: str
    metrics: tuple[Metric, ...]
    target: str
    coarse: EvaluationResult
    fine: EvaluationResult
    icp: EvaluationResult | None

    def by_method(self) -> dict[str, EvaluationResult]:
        """{'coarse': ..., 'fine': ..., 'ICP': ...} for what was evaluated."""
        out = {"coarse": self.coarse, "fine": self.fine}
        if self.icp is not None:
            out["ICP"] = self.icp
        return out


#: The last reference's layer fits: (reference, branches, parameters, layers). The fits depend on
#: those three alone and are the same for every transform and every target evaluated against that
#: reference, so the targets of one run share them (the evaluation stage passes the same branches).
_last_layers: tuple[Scan, list[CylinderFit], EvaluationParams, list] | None = None
_layers_lock = threading.Lock()


def _reference_layers(ref: Scan, branches: list[CylinderFit], evaluation: EvaluationParams) -> list:
    global _last_layers
    with _layers_lock:
        last = _last_layers
    if last is not None and last[0] is ref and last[1] is branches and last[2] == evaluation:
        return last[3]
    layers = reference_layers(ref, branches, evaluation=evaluation)
    with _layers_lock:
        _last_layers = (ref, branches, evaluation, layers)
    return layers


def evaluate_registration(ref: Scan, tgt: Scan, T_coarse: np.ndarray, T_fine: np.ndarray, icp: IcpResult | None, *,
                          evaluation: EvaluationParams, T_true: np.ndarray | None = None,
                          branches: list[CylinderFit] | None = None) -> PairReport:
    """The paper's evaluation of the coarse, fine and ICP transforms of `tgt` onto `ref`."""
    branches = find_branches(ref, evaluation=evaluation) if branches is None else branches
    layers = _reference_layers(ref, branches, evaluation)
    kw = dict(evaluation=evaluation, T_true=T_true, branches=branches, ref_layers=layers)
    ev_c = evaluate_pair(ref, tgt, T_coarse, **kw)
    ev_f = evaluate_pair(ref, tgt, T_fine, **kw)
    ev_i = None
    if icp is not None and icp.ran:
        ev_i = evaluate_pair(ref, tgt, icp.T_ref_target, **kw)
    rows: list[Metric] = []
    for label, ev in (("coarse", ev_c), ("fine", ev_f), ("ICP", ev_i)):
        if ev is not None:
            rows += [Metric(f"{label}: {m.description}", m.unit, m.value) for m in ev.metrics]
    return PairReport(ok=True, message="", metrics=tuple(rows), target=tgt.name, coarse=ev_c, fine=ev_f, icp=ev_i)
