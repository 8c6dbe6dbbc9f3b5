"""Monotone safeguard of the control design (thesis section 5.3, eq. 5.8-5.12).

The identification never loosens the bounds (eq. 5.4-5.5), but a controller redesigned for a
shifted midpoint can still give a larger mu-bar. Eq. (5.12) fixes that for any design method
``F``:

1. ``F(phi^{k+1})`` if its mu-bar is no larger than the previous iteration's;
2. else the box ``phi~`` expanded about the *previous* midpoint (eq. 5.8-5.11)::

       theta_hat = theta_hat^k,  delta = 2 max(theta_up^{k+1} - theta_hat, theta_hat - theta_lo^{k+1}),
       theta_up/lo = theta_hat +- delta / 2

   with ``F(phi~)`` if that is no worse;
3. else the previous controller ``C^k`` on ``phi~``. Because ``phi~`` has the previous nominal
   model and no larger intervals (it lies inside the previous analysis box), Lemma 2.2 gives
   ``mu(phi~, C^k) <= mu(phi^k, C^k)``.

The reported mu-bar is therefore non-increasing. In branch 3 we report
``min(mu(phi~, C^k), mu^k)`` so that the discretised frequency grid of the analysis cannot
break the guarantee by round-off.

The expanded box is used for the control design and analysis only; the identified bounds
(which the next identification starts from) are never widened.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from setmem_hil.model.modal_model import IntervalModel, ModalParameters

BRANCHES = ("new-design", "expanded", "previous-controller")

AnalyzeFn = Callable[[IntervalModel, Any], Any]
"""``analyze(model, controller)``: robust analysis with ``controller=None`` meaning "design
``F(model)``"; returns an object with ``mu_peak`` and ``controller`` (a RobustAnalysis)."""


@dataclass(frozen=True)
class SafeguardOutcome:
    """The design accepted at one iteration (eq. 5.12).

    Attributes
    ----------
    analysis : RobustAnalysis
        Analysis of the accepted (model, controller) pair; its ``controller`` is ``C^k``.
    analysis_model : IntervalModel
        ``phi^k`` as analysed: the identified box, or the expanded box ``phi~``.
    branch : str
        One of :data:`BRANCHES`.
    mu_peak : float
        Reported mu-bar (non-increasing over iterations).
    tried : dict
        mu-bar of every branch evaluated, by branch name.
    certified_mu : float
        The reported mu-bar as certified on the whole frequency band (``mu_peak (1 + 1e-4)``,
        issue 27), ``inf`` when it could not be: the campaign stops on this value.
    """

    analysis: Any
    analysis_model: IntervalModel
    branch: str
    mu_peak: float
    tried: dict
    certified_mu: float = math.inf

    @property
    def certified(self) -> bool:
        """The band-wide certificate holds (:attr:`certified_mu` is finite)."""
        return math.isfinite(self.certified_mu)


def certified_value(analysis: Any) -> float:
    """``analysis.certified_mu`` (a RobustAnalysis); test doubles with only ``mu_peak`` give that."""
    return float(getattr(analysis, "certified_mu", analysis.mu_peak))


def expanded_model(previous_midpoint: ModalParameters | np.ndarray, new_model: IntervalModel) -> IntervalModel:
    """The box of eq. (5.8)-(5.11): the new bounds, widened symmetric about the old midpoint.

    Parameters
    ----------
    previous_midpoint : ModalParameters or numpy.ndarray
        ``theta_hat^k``, shape ``(n_modes, 4)``.
    new_model : IntervalModel
        ``phi^{k+1}`` from the identification.

    Returns
    -------
    IntervalModel
        Centred on ``theta_hat^k`` and containing ``new_model``.

    Examples
    --------
    >>> import numpy as np
    >>> new = IntervalModel(np.array([[0.0, 1.0, 0.0, 3.0]]), np.array([[0.1, 2.0, 0.0, 4.0]]))
    >>> expanded_model(np.array([[0.05, 1.2, 0.0, 3.6]]), new).upper.tolist()
    [[0.1, 2.0, 0.0, 4.2]]
    """
    mid = previous_midpoint.values if isinstance(previous_midpoint, ModalParameters) else np.asarray(previous_midpoint, dtype=float)
    if mid.shape != new_model.lower.shape:
        raise ValueError(f"previous_midpoint: expected shape {new_model.lower.shape}, found {mid.shape}")
    half = np.maximum(new_model.upper - mid, mid - new_model.lower)  # delta / 2, eq. 5.9
    half = np.maximum(half, 0.0)
    return IntervalModel(mid - half, mid + half)  # eq. 5.10-5.11


def safeguarded_design(
    new_model: IntervalModel,
    previous: SafeguardOutcome | None,
    analyze: AnalyzeFn,
) -> SafeguardOutcome:
    """Design and analyse the controller of one iteration with the rule of eq. (5.12).

    Parameters
    ----------
    new_model : IntervalModel
        Identified bounds ``phi^{k+1}``.
    previous : SafeguardOutcome or None
        The previous iteration's outcome (None at the first iteration: plain design).
    analyze : callable
        ``analyze(model, controller)`` as in :data:`AnalyzeFn`.

    Returns
    -------
    SafeguardOutcome
    """
    first = analyze(new_model, None)
    tried = {"new-design": float(first.mu_peak)}
    if previous is None or first.mu_peak <= previous.mu_peak:
        return SafeguardOutcome(first, new_model, "new-design", float(first.mu_peak), tried, certified_value(first))
    phi = expanded_model(previous.analysis_model.midpoint, new_model)
    second = analyze(phi, None)
    tried["expanded"] = float(second.mu_peak)
    if second.mu_peak <= previous.mu_peak:
        return SafeguardOutcome(second, phi, "expanded", float(second.mu_peak), tried, certified_value(second))
    third = analyze(phi, previous.analysis.controller)
    tried["previous-controller"] = float(third.mu_peak)
    return SafeguardOutcome(third, phi, "previous-controller", float(min(third.mu_peak, previous.mu_peak)), tried,
                            min(certified_value(third), previous.certified_mu))


__all__ = ["BRANCHES", "SafeguardOutcome", "expanded_model", "safeguarded_design"]
