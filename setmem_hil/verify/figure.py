"""``verify.png``: the predicted band of ``|S|`` over the box, and the measured points (issue 45)."""

from __future__ import annotations

import numpy as np

from setmem_hil.robust.closed_loop_prediction import predicted_sensitivity
from setmem_hil.robust.implemented_loop import implemented_response

__all__ = ["write_figure"]


def write_figure(path, setup, result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w_points = np.array([p.measured.omega_rad_s for p in result.points])
    grid = np.geomspace(0.7 * w_points.min(), 1.4 * w_points.max(), 300)
    k = implemented_response(setup.controller, setup.fs_hz, setup.delay_samples, setup.prewarp_rad_s, grid)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    gains = sorted({p.gain for p in result.points})
    colors = plt.cm.viridis(np.linspace(0.15, 0.85, len(gains)))
    for gain, color in zip(gains, colors):
        band = np.array([predicted_sensitivity(setup.model, setup.weights, complex(kw), float(w), setup.calibration_gain,
                                               loop_gain=gain).abs_range for w, kw in zip(grid, k)])
        finite = np.isfinite(band[:, 1])
        ax.fill_between(grid[finite], band[finite, 0], band[finite, 1], color=color, alpha=0.25, label=f"predicted |S|, gain {gain:g}")
        mine = [p for p in result.points if p.gain == gain]
        for p in mine:
            m = p.measured
            look = dict(fmt="o", color=color, markersize=6) if p.inside else (
                dict(fmt="X", color="red", markersize=9) if p.outside else dict(fmt="s", color="grey", markersize=6))  # grey: uninformative
            ax.errorbar([m.omega_rad_s], [abs(m.S)], yerr=[[min(m.S_bound, abs(m.S) * 0.999)], [m.S_bound]], capsize=3, **look)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("frequency (rad/s)")
    ax.set_ylabel("|S| = |u / r|")
    outside = sum(p.outside for p in result.points)
    ax.set_title(f"closed loop at {setup.fs_hz:g} Hz, {setup.delay_samples} samples delay: "
                 + ("every informative point inside its prediction" if not outside else f"{outside} point(s) outside (red X)")
                 + (f"; {sum(not p.informative for p in result.points)} uninformative (grey)" if any(not p.informative for p in result.points) else ""))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
