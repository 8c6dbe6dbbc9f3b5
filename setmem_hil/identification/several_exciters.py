"""Guaranteed intervals of a structure seen by several exciters and sensors (issue 64, item 4;
thesis appendix A: "identify each input-output pair with shared poles").

Every input-output pair ``(sensor k, exciter l)`` is a frequency response of its own with the
structure's poles, so the pairs are the outputs of :func:`~setmem_hil.identification.algorithm.identify_outputs`
(shared ``a1, a0`` per mode; each pair's own ``b1, b0``): its guarantee, certificates and
partitioning are those of several sensors (issue 25), unchanged. The result is per mode the poles'
intervals and a residue *matrix* of intervals, ``b0[i, k, l]`` and ``b1[i, k, l]``.

The prior gives each mode's frequency and damping bands once (shared); its residue bounds are the
bounds of every pair's residue. A pair's sign is not known before identification (an exciter and
a sensor on opposite sides of a node see the mode with opposite signs), so each pair's ``b0``
interval is the prior's made symmetric about zero: ``[-B, B]`` with ``B`` the larger of
``|b0_min|``, ``|b0_max|`` (``b1`` likewise). That is our choice where the thesis is silent.

Then each real mode's residue matrix is contracted by its rank (``B0 = psi phi^T``,
:mod:`setmem_hil.identification.rank_one`): a pair that sees a mode poorly, or was never measured,
is bounded by the pairs that see it well. Only where the prior fixes ``b1 = 0`` (real modes); a
mode whose box holds no rank-one matrix keeps its box and is said not to be one real mode
(``rank_one_consistent`` False). Not used yet: the rank inside the cone programs, where it would
also narrow the poles. Cost: the pairs are solved as outputs, so a close pair of modes (the
two-plane beam) takes the several-output path without the close-mode groups of one output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.identification.algorithm import IdentifySettings, identify_outputs
from setmem_hil.identification.rank_one import contract_rank_one
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_matrix import ModalMatrix
from setmem_hil.model.modal_model import A0, A1, B0, B1
from setmem_hil.model.prior import Prior

__all__ = ["MatrixIdentification", "identify_matrix", "pair_prior"]


@dataclass(frozen=True)
class MatrixIdentification:
    """The poles' intervals ``(n_modes, 2)`` as ``(a1, a0)`` and the residue matrices' intervals
    ``(n_modes, n_sensors, n_exciters)``; ``verified`` per mode over every pair."""

    lower_poles: np.ndarray
    upper_poles: np.ndarray
    lower_b1: np.ndarray
    upper_b1: np.ndarray
    lower_b0: np.ndarray
    upper_b0: np.ndarray
    sensors: tuple[str, ...]
    exciters: tuple[str, ...]
    verified: np.ndarray
    n_solves: int
    # per mode: True / False whether a rank-one residue matrix fits the box (contracted when True);
    # None where the rank was not used (b1 not fixed at zero: a complex mode)
    rank_one_consistent: tuple[bool | None, ...] = ()

    def contains(self, truth: ModalMatrix) -> bool:
        """Does every interval hold ``truth``'s poles and every pair's residues?"""
        poles = truth.modes.values[:, [A1, A0]]
        if not np.all((self.lower_poles <= poles) & (poles <= self.upper_poles)):
            return False
        for k in range(len(self.sensors)):
            for l in range(len(self.exciters)):
                pair = truth.pair(k, l).values
                for col, lo, hi in ((B1, self.lower_b1, self.upper_b1), (B0, self.lower_b0, self.upper_b0)):
                    if not np.all((lo[:, k, l] <= pair[:, col]) & (pair[:, col] <= hi[:, k, l])):
                        return False
        return True

    def to_document(self) -> dict:
        """``{"sensors", "exciters", "modes": [{"a1": [lo, hi], "a0": [lo, hi], "b0": [[[lo, hi] per
        exciter] per sensor], "b1": ..., "verified"}]}``."""
        modes = []
        for i in range(self.lower_poles.shape[0]):
            def matrix(lo, hi):
                return [[[float(lo[i, k, l]), float(hi[i, k, l])] for l in range(len(self.exciters))] for k in range(len(self.sensors))]
            modes.append({"a1": [float(self.lower_poles[i, 0]), float(self.upper_poles[i, 0])],
                          "a0": [float(self.lower_poles[i, 1]), float(self.upper_poles[i, 1])],
                          "b0": matrix(self.lower_b0, self.upper_b0), "b1": matrix(self.lower_b1, self.upper_b1),
                          "verified": bool(self.verified[i])})
            if i < len(self.rank_one_consistent):
                modes[-1]["rank_one_consistent"] = self.rank_one_consistent[i]
        return {"sensors": list(self.sensors), "exciters": list(self.exciters), "modes": modes}


def pair_prior(prior: Prior) -> Prior:
    """The prior of one pair: the modes' bands as given, each residue bound made symmetric about
    zero (module docstring)."""
    def symmetric(lo: float, hi: float) -> tuple[float, float]:
        if lo == hi == 0.0:
            return 0.0, 0.0  # fixed at zero (b1 = 0): every pair's is zero too
        bound = max(abs(lo), abs(hi))
        return -bound, bound

    modes = []
    for m in prior.modes:
        b1_min, b1_max = symmetric(m.b1_min, m.b1_max)
        b0_min, b0_max = symmetric(m.b0_min, m.b0_max)
        modes.append(replace(m, b1_min=b1_min, b1_max=b1_max, b0_min=b0_min, b0_max=b0_max))
    return replace(prior, modes=tuple(modes))


def identify_matrix(columns: dict[tuple[int, int], FrequencyData], prior: Prior, sensors: tuple[str, ...],
                    exciters: tuple[str, ...], settings: IdentifySettings = IdentifySettings()) -> MatrixIdentification:
    """Shared poles and per-pair residues from the FRF matrix's measured pairs.

    ``columns[(k, l)]``: the data of sensor ``k`` driven by exciter ``l`` (every pair once; a pair
    never measured is left out, and its residues keep the prior's bounds)."""
    if not columns:
        raise InputFormatError("identify", "pairs", "no input-output pair measured")
    for k, l in columns:
        if not (0 <= k < len(sensors) and 0 <= l < len(exciters)):
            raise InputFormatError("identify", "pairs", f"pair ({k}, {l}) is not a (sensor, exciter) of {list(sensors)} x {list(exciters)}")
        if any(not math.isfinite(b) or b < 0 for b in columns[(k, l)].bound):
            raise InputFormatError("identify", f"{sensors[k]} <- {exciters[l]}", "every bound finite and non-negative")
    pairs = sorted(columns)
    per_pair = pair_prior(prior)
    names = [f"{sensors[k]} <- {exciters[l]}" for k, l in pairs]
    result = identify_outputs([columns[p] for p in pairs], [per_pair] * len(pairs), names, settings=settings)
    n, shape = prior.n_modes, (prior.n_modes, len(sensors), len(exciters))
    bounds = {name: (np.empty(shape), np.empty(shape)) for name in ("b1", "b0")}
    for name, col, (lo_attr, hi_attr) in (("b1", B1, ("b1_min", "b1_max")), ("b0", B0, ("b0_min", "b0_max"))):
        lo, hi = bounds[name]
        for i, m in enumerate(per_pair.modes):  # pairs never measured: the prior's bounds
            lo[i], hi[i] = getattr(m, lo_attr), getattr(m, hi_attr)
        for (k, l), model in zip(pairs, result.models):
            lo[:, k, l], hi[:, k, l] = model.lower[:, col], model.upper[:, col]
    rank_one = _contract_real_modes(prior, *bounds["b0"])
    first = result.models[0]
    return MatrixIdentification(first.lower[:, [A1, A0]].copy(), first.upper[:, [A1, A0]].copy(), *bounds["b1"], *bounds["b0"],
                                tuple(sensors), tuple(exciters), np.asarray(result.verified, dtype=bool), int(result.n_solves),
                                rank_one)


def _contract_real_modes(prior: Prior, lo: np.ndarray, hi: np.ndarray) -> tuple[bool | None, ...]:
    """Each real mode's (``b1`` fixed at zero by the prior) ``b0`` matrix contracted by its rank,
    in place (:func:`~setmem_hil.identification.rank_one.contract_rank_one`); per mode whether a
    rank-one matrix fits its box (None: not a real mode, not contracted)."""
    consistent: list[bool | None] = []
    for i, m in enumerate(prior.modes):
        if not (m.b1_min == m.b1_max == 0.0):
            consistent.append(None)
            continue
        contracted = contract_rank_one(lo[i], hi[i])
        lo[i], hi[i] = contracted.lower, contracted.upper
        consistent.append(contracted.consistent)
    return tuple(consistent)
