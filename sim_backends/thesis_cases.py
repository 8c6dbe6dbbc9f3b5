"""Data sets of the thesis's identification examples (section 6.2) on the simulated beam.

The thesis takes "the 5 data points closest to the peak in the frequency response" of each of
the first three modes (6.2.1) without saying on which grid. We use a 400-point log-spaced grid
from 0.1 to 100 rad/s: with it the interval widths come out between 0.4 and 1.5 times those of
Table 6-4 (denser grids put points closer to the peaks and give narrower intervals).
"""

from __future__ import annotations

import numpy as np

from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

SECTION_6_2_GRID = np.geomspace(0.1, 100.0, 400)

# Table 6-4 (b1 = 0): lower and upper bounds of a1, a0, b0 for modes 1-3
TABLE_6_4 = {
    "a1_1": (1.9211e-2, 2.0921e-2), "a0_1": (9.9946e-1, 1.0005), "b0_1": (3.8806, 4.1480),
    "a1_2": (1.1428e-1, 1.3777e-1), "a0_2": (3.9241e1, 3.9326e1), "b0_2": (3.7375, 4.3394),
    "a1_3": (2.8057e-1, 4.5110e-1), "a0_3": (3.0731e2, 3.0854e2), "b0_3": (3.4042, 4.8278),
}
# Table 6-2 (b1 free): widths of the same parameters and of b1
TABLE_6_2 = {
    "a1_1": (1.9222e-2, 2.0931e-2), "a0_1": (9.9911e-1, 1.0008), "b1_1": (-1.3869e-1, 1.2570e-1), "b0_1": (3.8820, 4.1493),
    "a1_2": (1.1278e-1, 1.3975e-1), "a0_2": (3.9200e1, 3.9369e1), "b1_2": (-5.6459e-2, 4.7304e-2), "b0_2": (3.6984, 4.3906),
    "a1_3": (2.6480e-1, 4.7965e-1), "a0_3": (3.0599e2, 3.0970e2), "b1_3": (-4.4073e-2, 5.8050e-2), "b0_3": (3.2468, 5.0450),
}


def peak_frequencies(n_per_mode: int = 5, n_modes: int = 3, grid: np.ndarray = SECTION_6_2_GRID) -> np.ndarray:
    """The ``n_per_mode`` grid points nearest each of the first ``n_modes`` natural frequencies."""
    wn = beam_parameters().natural_frequencies[:n_modes]
    chosen = [grid[np.argsort(np.abs(np.log(grid / w)))[:n_per_mode]] for w in wn]
    return np.sort(np.concatenate(chosen))


def section_6_2_data(seed: int) -> tuple[FrequencyData, SimulatedBeamExperiment]:
    """15 points, noise bound of section 6.2 (fully damped shape) plus |W1|, 8-mode truth."""
    beam = SimulatedBeamExperiment(noise_profile="fully_damped", seed=seed)
    return FrequencyData.from_measurements(beam.measure_many(peak_frequencies())), beam
