"""Stability diagram of a modal estimate: poles per model order over the FRF magnitude."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from setmem_hil.estimation.modal_estimate import ModalEstimate
from setmem_hil.io.atomic_file import atomic_path
from setmem_hil.model.frequency_data import FrequencyData


def plot_stability_diagram(estimate: ModalEstimate, data: FrequencyData, path: str | Path) -> Path:
    """PNG: LSCF poles (damping 0-30 %) per model order, |G| on a second axis, the chosen poles marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5))
    lo, hi = estimate.band_rad_s
    for order, w, z in zip(estimate.orders, estimate.pole_omegas, estimate.pole_zetas):
        keep = (w >= lo) & (w <= hi) & (z > 0) & (z < 0.3)
        ax.plot(w[keep] / (2 * math.pi), order[keep], ".", color="0.55", ms=3)
    top = max((float(np.max(o)) for o in estimate.orders if len(o)), default=1.0)
    for col in estimate.stable:  # the diagram's stable columns (issue 47), chosen or not
        ax.plot([col.omega_rad_s / (2 * math.pi)], [top + 1.5], "v", color="tab:green", ms=7)
    for m in estimate.modes:
        if not m.low_pseudo_mode:
            ax.axvline(m.omega_n_rad_s / (2 * math.pi), color="tab:red", lw=1, alpha=0.8)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("model order (LSCF)")
    ax.set_xlim(lo / (2 * math.pi), hi / (2 * math.pi))
    twin = ax.twinx()
    inside = (data.omega_rad_s >= lo) & (data.omega_rad_s <= hi)
    twin.semilogy(data.omega_rad_s[inside] / (2 * math.pi), np.abs(data.response[inside]), color="tab:blue", lw=1)
    twin.set_ylabel("|G| (receptance, data units)")
    ax.set_title("Stability diagram: poles per order (grey), stable columns (green), chosen (red), |G| (blue)", fontsize=10)
    fig.tight_layout()
    out = Path(path)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return out
