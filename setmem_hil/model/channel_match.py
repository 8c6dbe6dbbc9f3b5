"""A channel match (issue 26): each oscilloscope channel's gain at each vertical scale relative
to one reference, as measured by ``setmem-hil calibrate-channels``
(:mod:`setmem_hil.estimation.channel_match` says how, :mod:`setmem_hil.io.channel_match_file`
how it is stored)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ChannelGain", "ChannelMatch", "scale_key"]


@dataclass(frozen=True)
class ChannelGain:
    """``gain``: channel ``channel``'s gain at ``scale_v`` over the reference's; the true ratio is
    within ``gain x (1 +- bound)``."""

    channel: int
    scale_v: float
    gain: float
    bound: float


def scale_key(channel: int, scale_v: float) -> tuple[int, float]:
    return int(channel), float(f"{scale_v:.6g}")


@dataclass(frozen=True)
class ChannelMatch:
    """A calibration: the gains and where they were measured.

    ``identity``: the scope's ``*IDN?`` reply; ``frequency_hz``: the tee'd sine's frequency;
    ``utc``: when (ISO 8601); ``reference``: ``(channel, scale_v)`` whose gain is 1."""

    identity: str
    frequency_hz: float
    utc: str
    reference: tuple[int, float]
    gains: tuple[ChannelGain, ...]

    def gain(self, channel: int, scale_v: float) -> ChannelGain | None:
        """The entry of ``channel`` at ``scale_v`` (scales compared to 6 digits), None if not calibrated."""
        key = scale_key(channel, scale_v)
        return next((g for g in self.gains if scale_key(g.channel, g.scale_v) == key), None)

    def scales(self, channel: int) -> tuple[float, ...]:
        return tuple(sorted(g.scale_v for g in self.gains if g.channel == channel))
