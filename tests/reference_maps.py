"""Map quantities computed independently of the package, with NumPy and SciPy, for tests."""

from __future__ import annotations

import numpy as np
from scipy.special import gammaln


def expected_std(k: np.ndarray, S: np.ndarray) -> np.ndarray:
    """E[h^-1/2] for h ~ Gamma(k/2, rate S/2) (k > 1), sqrt(S/k) for 0 < k <= 1, NaN else."""
    with np.errstate(divide="ignore", invalid="ignore"):
        bayes = np.sqrt(S / 2) * np.exp(gammaln((k - 1) / 2) - gammaln(k / 2))
        return np.where(k > 1, bayes, np.where(k > 0, np.sqrt(S / k), np.nan))
