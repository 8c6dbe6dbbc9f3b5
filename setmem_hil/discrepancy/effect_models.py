"""One class per candidate effect a modal model may lack: response, Jacobian, removal from data.

Each one-parameter effect ``p`` augments the modal response ``G`` (eq. 3.6):

``TimeDelay`` (``tau`` s)
    ``G e^{-s tau}``: acquisition latency.
``FirstOrderLag`` (``tau`` s)
    ``G / (tau s + 1)``: sensor or actuator bandwidth.
``Feedthrough`` (``d``)
    ``G + d``: residual flexibility of modes above the band (the upper residual).
``ResidualMass`` (``r``)
    ``G + r / s^2``: mass line of modes below the band (the lower residual).

and :class:`ExtraMode` adds a mode ``(b1 s + b0) / (s^2 + a1 s + a0)`` (its Jacobian is the
modal one, eq. 3.9). Every user of an effect goes through these classes: the minimax fit
(:mod:`setmem_hil.discrepancy.fit`: ``response_and_jacobian``), the re-identification with
the effect removed (:mod:`setmem_hil.discrepancy.reidentify`: ``remove``, with the bound
widened to cover the parameter's interval), and the simulated hidden effects
(:mod:`setmem_hil.sim_backends.hidden_effects`: ``apply``). A new candidate is one more class
registered in :data:`EFFECT_MODELS`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["EffectModel", "TimeDelay", "FirstOrderLag", "Feedthrough", "ResidualMass", "ExtraMode", "EFFECT_MODELS"]


class EffectModel:
    """A one-parameter augmentation ``G -> F(G, s, p)`` of the modal response."""

    name: str = ""
    param_names: tuple[str, ...] = ()
    lower_limit: float = 0.0
    """Smallest admissible parameter value (a delay or a time constant is >= 0)."""

    def response_and_jacobian(self, g_modal: np.ndarray, s: np.ndarray, p: float):
        """``(F, dF/dG or None when 1, dF/dp)`` at ``s = j omega``."""
        raise NotImplementedError

    def apply(self, g_modal: np.ndarray, s: np.ndarray, p: float) -> np.ndarray:
        """The effect-laden response."""
        return self.response_and_jacobian(g_modal, s, p)[0]

    def remove(self, data: FrequencyData, value: float, delta: float = 0.0) -> FrequencyData:
        """Data with the effect removed at ``value`` and the bound covering ``|p' - value| <= delta``."""
        raise NotImplementedError

    def typical_step(self, data: FrequencyData) -> float:
        """A parameter step that changes the response by about a percent (interval search)."""
        return 0.01 / float(np.max(data.omega_rad_s))


@dataclass(frozen=True)
class TimeDelay(EffectModel):
    name: str = "time_delay"
    param_names: tuple[str, ...] = ("tau",)

    def response_and_jacobian(self, g_modal, s, p):
        e = np.exp(-s * p)
        return g_modal * e, e, -s * g_modal * e

    def remove(self, data, value, delta=0.0):
        w, g, R = data.omega_rad_s, data.response, data.bound
        phase = np.minimum(w * delta / 2.0, np.pi / 2.0)
        return FrequencyData(w, g * np.exp(1j * w * value), R + (np.abs(g) + R) * 2.0 * np.sin(phase))


@dataclass(frozen=True)
class FirstOrderLag(EffectModel):
    name: str = "first_order_lag"
    param_names: tuple[str, ...] = ("tau",)

    def response_and_jacobian(self, g_modal, s, p):
        lag = 1.0 / (p * s + 1.0)
        return g_modal * lag, lag, -s * g_modal * lag**2

    def remove(self, data, value, delta=0.0):
        w, g, R = data.omega_rad_s, data.response, data.bound
        factor = 1.0 + 1j * w * value
        return FrequencyData(w, g * factor, R * np.abs(factor) + (np.abs(g) + R) * w * delta)


@dataclass(frozen=True)
class Feedthrough(EffectModel):
    name: str = "feedthrough"
    param_names: tuple[str, ...] = ("d",)
    lower_limit: float = -np.inf

    def response_and_jacobian(self, g_modal, s, p):
        return g_modal + p, None, 1.0

    def remove(self, data, value, delta=0.0):
        return FrequencyData(data.omega_rad_s, data.response - value, data.bound + delta)

    def typical_step(self, data):
        return 0.1 * float(np.median(data.bound))


@dataclass(frozen=True)
class ResidualMass(EffectModel):
    """``G + r / s^2``: the lower residual (mass line) of modes below the band, as in modal-analysis
    practice (``-r / omega^2`` in receptance; ``r = 1 / m`` of a rigid-body mode)."""

    name: str = "residual_mass"
    param_names: tuple[str, ...] = ("r",)
    lower_limit: float = -np.inf

    def response_and_jacobian(self, g_modal, s, p):
        inv = 1.0 / (s * s)
        return g_modal + p * inv, None, inv

    def remove(self, data, value, delta=0.0):
        w = data.omega_rad_s
        return FrequencyData(w, data.response + value / w**2, data.bound + delta / w**2)

    def typical_step(self, data):
        return 0.1 * float(np.median(data.bound * data.omega_rad_s**2))


@dataclass(frozen=True)
class ExtraMode:
    """An added mode; fitted and identified as a mode (its Jacobian is eq. 3.9's)."""

    name: str = "extra_mode"
    param_names: tuple[str, ...] = ("a1", "a0", "b1", "b0")

    @staticmethod
    def apply(g_modal: np.ndarray, s: np.ndarray, omega_n: float, zeta: float, b0: float, b1: float = 0.0) -> np.ndarray:
        return g_modal + (b1 * s + b0) / (s * s + 2 * zeta * omega_n * s + omega_n * omega_n)


EFFECT_MODELS: dict[str, EffectModel] = {m.name: m for m in (TimeDelay(), FirstOrderLag(), Feedthrough(), ResidualMass())}
"""The one-parameter effects by name (the extra mode is :class:`ExtraMode`)."""
