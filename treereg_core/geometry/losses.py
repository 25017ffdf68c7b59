"""Robust losses for iteratively reweighted least squares (the fine stage's adjustments)."""

from __future__ import annotations

import numpy as np


def robust_weight(res: np.ndarray, scale: float, loss: str) -> np.ndarray:
    """IRLS weight rho'(z), z = (res / scale)^2, of soft-L1 (2 (sqrt(1 + z) - 1)) or Cauchy (ln(1 + z))."""
    z = (res / scale) ** 2
    return 1.0 / np.sqrt(1.0 + z) if loss == "soft_l1" else 1.0 / (1.0 + z)


def robust_cost(res: np.ndarray, scale: float, loss: str, weights: np.ndarray | None = None) -> float:
    """Sum of rho(z) * scale^2 for the loss of `robust_weight` (each term times `weights`, if given)."""
    z = (res / scale) ** 2
    rho = 2.0 * (np.sqrt(1.0 + z) - 1.0) if loss == "soft_l1" else np.log1p(z)
    return float(rho.sum() if weights is None else rho @ weights) * scale ** 2
