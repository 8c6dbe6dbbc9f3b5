"""The checks a run makes before its first dwell that need no rig (``run --check``, thesis section 3.4).

Kept free of the loop's numerics at import, so ``run --check`` answers at once.
"""

from __future__ import annotations

import re

from setmem_hil.errors import InputFormatError
from setmem_hil.io.procedure import Procedure

__all__ = ["preflight"]


def preflight(procedure: Procedure) -> None:
    """Every check a run makes before its first dwell that does not need the rig (``run --check``).

    The procedure file is validated when it is loaded (schema, keys, transport options, safety
    limits); this adds what depends on the prior and the initial design together: the residues of
    modes without ``b0`` bounds must be boundable from measurements at the ``[initial]``
    frequencies (the residue bootstrap's coupling depends on the frequencies and the prior's poles
    only, so it is decided before measuring), else the campaign would measure every initial point
    and then stop.
    """
    import numpy as np

    from setmem_hil.identification.residue_bootstrap import bootstrap_residue_bounds
    from setmem_hil.model.frequency_data import FrequencyData

    source = procedure.source_path or procedure.name
    if procedure.backend.kind == "instruments":  # every profile loads and fits its role
        from setmem_hil.drivers.instruments.instrument_set import check_instruments

        check_instruments(procedure)
    modes = procedure.prior.modes
    w = np.asarray(procedure.initial_omegas_rad_s, dtype=float)
    probe = FrequencyData(w, np.zeros(w.size, complex), np.zeros(w.size))
    try:
        bootstrap_residue_bounds(probe, procedure.prior.initial_bounds())
    except InputFormatError as exc:
        overlaps = [f"[[mode]] {i} and {i + 1} ({modes[i - 1].omega_min:g}-{modes[i - 1].omega_max:g} and "
                    f"{modes[i].omega_min:g}-{modes[i].omega_max:g} rad/s)"
                    for i in range(1, len(modes)) if modes[i].omega_min < modes[i - 1].omega_max]
        cause = f"; the bands of {', '.join(overlaps)} overlap" if overlaps else ""
        cause += _looks_like_hz(w, [(m.omega_min, m.omega_max) for m in modes])
        coupling = re.search(r"mode coupling [^)]*", exc.problem)
        raise InputFormatError(source, "[[mode]] / [initial]",
                               f"the residues cannot be bounded from measurements at the [initial] frequencies"
                               f"{f' ({coupling.group(0)})' if coupling else ''}{cause}; give b0_min/b0_max, separate the "
                               "bands or move initial points nearer the resonances") from None


def _looks_like_hz(initial, bands: list[tuple[float, float]]) -> str:
    """A cause to name when the [initial] frequencies or the [[mode]] bands look like hertz: the
    initial points sit far more often at a mode's band (within a factor 1.5) once one side is
    multiplied by 2 pi (issue 40: a Hz list was caught, but explained as a mode coupling)."""
    import numpy as np

    def near(w) -> float:
        return float(np.mean([any(lo / 1.5 <= x <= hi * 1.5 for lo, hi in bands) for x in w])) if len(w) else 0.0

    given, initial_hz, bands_hz = near(initial), near(np.asarray(initial) * 2 * np.pi), near(np.asarray(initial) / (2 * np.pi))
    if max(initial_hz, bands_hz) < 0.6 or max(initial_hz, bands_hz) < given + 0.3:
        return ""
    if initial_hz >= bands_hz:
        return ("; the [initial] frequencies look like Hz: times 2 pi they sit at the modes' bands (they are rad/s; "
                "or give them in Hz as omega_hz = [...])")
    return ("; the [[mode]] bands look like Hz: the [initial] frequencies sit at them divided by 2 pi (omega_min and "
            "omega_max are rad/s; or give omega_min_hz / omega_max_hz)")
