"""Measure a channel match (``setmem-hil calibrate-channels``, issue 26) through a BNC tee.

The technician disconnects the shaker amplifier and the sensors from the oscilloscope and wires
the generator's output through a tee to every channel the procedure uses. Then:

1. with the output off, each channel's noise floor (the quantization bound counts on it);
2. a sine at :data:`FREQUENCY_HZ`, for every coarse V/div step of the profile the generator can
   fill (at most ``max_drive_v``, never more than the campaign itself may send): one record with
   every channel at that step, and one with the reference channel there and the others one step
   up (the link from a step to the next); each fills :data:`FILL` of the half screen;
3. the gains solved with their guaranteed bounds (:mod:`setmem_hil.estimation.channel_match`);
4. the output off, read back, whatever happened.

Steps the generator cannot fill to :data:`MIN_FILL` are left out: a campaign that ranges there
falls back to the datasheet's gain accuracy for that point.
"""

from __future__ import annotations

import datetime
from typing import Callable

from setmem_hil.drivers.instruments.scpi_scope import ScpiScope
from setmem_hil.drivers.instruments.source import SignalSource, switch_output_off
from setmem_hil.estimation.channel_errors import adc_code
from setmem_hil.estimation.channel_match import MatchRecord, amplitude_error_bound, fit_amplitude, solve_channel_match
from setmem_hil.errors import DataQualityError, DeviceError
from setmem_hil.model.channel_match import ChannelMatch

__all__ = ["measure_channel_match", "match_plan", "FREQUENCY_HZ"]

FREQUENCY_HZ = 1000.0  # far below every profile's bandwidth (the gains are flat there) and many periods per record
RECORD_S = 0.2
POINTS_PER_PERIOD = 50
FILL = 0.8  # of the half screen: room for the generator's amplitude error without clipping
MIN_FILL = 0.25


def match_plan(scales_v: tuple[float, ...], channels: tuple[int, ...], reference: int, half_screen_div: float,
               amplitude_limits_v: tuple[float, float]) -> list[tuple[dict[int, float], float]]:
    """``[(scales of each channel, sine amplitude in volts), ...]`` (module docstring, step 2)."""
    lo, hi = amplitude_limits_v
    usable = [s for s in scales_v if lo <= FILL * half_screen_div * s and min(hi, FILL * half_screen_div * s) >= MIN_FILL * half_screen_div * s]
    plan = []
    for k, scale in enumerate(usable):
        amplitude = min(hi, FILL * half_screen_div * scale)
        plan.append(({c: scale for c in channels}, amplitude))
        if k + 1 < len(usable) and len(channels) > 1:
            plan.append(({c: (scale if c == reference else usable[k + 1]) for c in channels}, amplitude))
    return plan


def _record(scope: ScpiScope, scales: dict[int, float], noise_div: dict[int, float]) -> MatchRecord:
    for ch, scale in scales.items():
        if scope.scales_v.get(ch) != scale:
            scope.set_vertical_scale(ch, scale)
    record = scope.record(RECORD_S, POINTS_PER_PERIOD * FREQUENCY_HZ)
    p = scope.profile
    amplitudes, bounds = {}, {}
    for ch, scale in scales.items():
        amplitude, _ = fit_amplitude(record.t_s, record.volts[ch], FREQUENCY_HZ)
        code_v = adc_code(p.divisions * scale, p.adc_bits)
        amplitudes[ch] = amplitude
        bounds[ch] = amplitude_error_bound(amplitude, record.volts[ch].size, noise_div.get(ch, 0.0) * scale, code_v)
    return MatchRecord(dict(scales), amplitudes, bounds)


def measure_channel_match(source: SignalSource, scope: ScpiScope, reference: int, max_drive_v: float, reference_peak_v: float,
                          progress: Callable[[int, int], None] = lambda done, total: None) -> ChannelMatch:
    """The channel match of ``scope.channels`` against channel ``reference`` at the smallest
    scale holding ``reference_peak_v`` (the force the campaign levels to: its points then carry
    no gain bound of the force channel). The generator's output is off at the end, read back."""
    identity = scope.check_identity()
    try:
        source.set_output(False)
        noise_div = scope.noise_floor_divisions()
        lo, hi = source.amplitude_limits_v
        plan = match_plan(tuple(scope.profile.vertical_scales_v), scope.channels, reference, scope.profile.divisions / 2.0,
                          (lo, min(hi, max_drive_v)))
        if not plan:
            raise DeviceError(f"{scope.where}: the generator ({lo:g}-{min(hi, max_drive_v):g} V, max_drive_v included) cannot fill "
                              f"{MIN_FILL:.0%} of any vertical scale's half screen")
        source.set_frequency_hz(FREQUENCY_HZ)
        records = []
        for i, (scales, amplitude) in enumerate(plan):
            source.set_amplitude_v(amplitude)
            if i == 0:
                source.set_output(True)
            records.append(_record(scope, scales, noise_div))
            progress(i + 1, len(plan))
    finally:
        switch_output_off(source, f"{source.name}")
    scales = sorted({s for scales, _ in plan for s in scales.values()})
    ref_scale = next((s for s in scales if FILL * scope.profile.divisions / 2.0 * s >= reference_peak_v), scales[-1])
    try:
        gains = solve_channel_match(records, (reference, ref_scale))
    except ValueError as exc:
        raise DataQualityError(f"{scope.where}: {exc}") from None
    utc = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    return ChannelMatch(identity, FREQUENCY_HZ, utc, (reference, ref_scale), tuple(gains))
