"""The compensator's files: JSON, MATLAB .mat, second-order sections as CSV, and a C99 header.

Contract (``setmem-hil controller RUN_DIR --out FILE``; README "From the campaign to the real-time
target"). Every form states the feedback sign: **positive feedback, ``u = K y``** (thesis 6.3.2,
footnote 3): the drive sample is ``+K`` applied to the sensor sample.

* JSON: ``sign`` (``"positive"``), ``iteration``, ``mu_peak``, ``design`` (``"robust"`` or ``"h2"``:
  which design made it, issue 38), ``margin`` (``1 / mu_peak``: how far the box could grow),
  ``continuous`` ``{A, B, C, D}``
  (rad/s time base), ``poles`` and ``zeros`` (``[re, im]`` pairs), ``gain``; with a sample rate
  also ``discrete`` ``{A, B, C, D, Ts, prewarp_rad_s}``, ``sos`` (rows ``[b0, b1, b2, a0, a1,
  a2]``) and ``sos_gain`` (the gain left outside the sections: 1.0, as the gain is folded into the
  first section, so ``scipy.signal.sosfilt(sos, x)`` is the drive).
* .mat (``scipy.io.savemat``): ``A, B, C, D, Ts, sign`` (the discrete compensator with ``Ts > 0``
  when a sample rate is given, else the continuous one with ``Ts = 0``), ``Ac, Bc, Cc, Dc`` (always
  continuous), ``sos, sos_gain`` (with a sample rate), ``iteration, mu_peak, design``.
* CSV: header ``b0,b1,b2,a0,a1,a2``, one row per section; a comment line before it gives the
  gain, the sample period and the sign.
* C: one header, standard headers only, ``double`` arithmetic, direct form II transposed
  biquads; ``setmem_controller_state``, ``setmem_controller_init``, ``setmem_controller_step``.
"""

from __future__ import annotations

import io
import math
from typing import Any

import numpy as np

__all__ = ["FORMATS", "format_for", "controller_document", "sos_csv", "c_header", "mat_variables"]

FORMATS = {".json": "json", ".mat": "mat", ".csv": "sos", ".h": "c"}


def format_for(path: str, explicit: str | None) -> str | None:
    """``--format`` if given, else from the file's extension (None: unknown)."""
    if explicit:
        return explicit
    for suffix, name in FORMATS.items():
        if str(path).lower().endswith(suffix):
            return name
    return None


def _matrix(a) -> list:
    return np.atleast_2d(np.asarray(a, dtype=float)).tolist() if np.size(a) else []


def _pairs(values) -> list:
    return [[float(np.real(v)), float(np.imag(v))] for v in np.asarray(values)]


def controller_document(*, iteration: int, mu_peak: float, continuous, zpk, discrete=None, prewarp_rad_s=None,
                        sos=None, sos_gain=None, design: str = "h2") -> dict[str, Any]:
    """The JSON document (see the module docstring)."""
    doc: dict[str, Any] = {
        "sign": "positive",
        "convention": "positive feedback: u = K y (drive = +K applied to the sensor signal)",
        "iteration": int(iteration),
        "mu_peak": float(mu_peak),
        "design": str(design),
        "margin": float(1.0 / mu_peak) if mu_peak > 0 and np.isfinite(mu_peak) else None,
        "continuous": {name: _matrix(getattr(continuous, name)) for name in "ABCD"},
        "poles": _pairs(zpk.poles),
        "zeros": _pairs(zpk.zeros),
        "gain": float(zpk.gain),
    }
    if discrete is not None:
        doc["discrete"] = {**{name: _matrix(getattr(discrete, name)) for name in "ABCD"}, "Ts": float(discrete.dt),
                           "prewarp_rad_s": float(prewarp_rad_s)}
        doc["sos"] = np.asarray(sos, dtype=float).tolist()
        doc["sos_gain"] = float(sos_gain)
    return doc


def mat_variables(doc: dict) -> dict[str, Any]:
    """The .mat file's variables from the JSON document."""
    cont = doc["continuous"]
    out: dict[str, Any] = {"sign": "positive", "iteration": doc["iteration"], "mu_peak": doc["mu_peak"],
                           "design": doc.get("design", "h2"),
                           **{f"{k}c": np.asarray(cont[k], dtype=float) for k in "ABCD"}}
    if "discrete" in doc:
        out.update({k: np.asarray(doc["discrete"][k], dtype=float) for k in "ABCD"})
        out.update(Ts=doc["discrete"]["Ts"], sos=np.asarray(doc["sos"], dtype=float), sos_gain=doc["sos_gain"])
    else:
        out.update({k: np.asarray(cont[k], dtype=float) for k in "ABCD"})
        out["Ts"] = 0.0
    return out


def sos_csv(doc: dict) -> str:
    buf = io.StringIO()
    buf.write(f"# sos_gain={doc['sos_gain']!r}, Ts={doc['discrete']['Ts']!r} s, sign=positive (u = K y), "
              f"iteration {doc['iteration']}\n")
    buf.write("b0,b1,b2,a0,a1,a2\n")
    for row in doc["sos"]:
        buf.write(",".join(repr(float(x)) for x in row) + "\n")
    return buf.getvalue()


def c_header(doc: dict) -> str:
    """A self-contained C99 header: the sections, their gain and the step function."""
    sos = np.asarray(doc["sos"], dtype=float)
    n = sos.shape[0]
    rows = ",\n".join("    {" + ", ".join(repr(float(x)) for x in (r[0], r[1], r[2], r[4], r[5])) + "}" for r in sos)
    Ts = float(doc["discrete"]["Ts"])
    if n == 0:
        raise ValueError("a static compensator has no sections: use its D matrix")
    return f"""/* setmem-hil compensator, iteration {doc['iteration']} ({doc.get('design', 'h2')} design, mu-bar {doc['mu_peak']:.6g}).
 * Discrete time: Ts = {Ts!r} s (fs = {1.0 / Ts:.9g} Hz), Tustin prewarped at {doc['discrete']['prewarp_rad_s']:.9g} rad/s.
 * Feedback sign: POSITIVE, u = K y: call setmem_controller_step(&s, y) once per sample with the
 * sensor sample y; its return value is the drive sample u (add it, do not subtract it).
 * {n} second-order sections, direct form II transposed, double precision (as scipy.signal.sosfilt).
 * Generated by setmem-hil; C99, standard headers only.
 */
#ifndef SETMEM_CONTROLLER_H
#define SETMEM_CONTROLLER_H

#include <stddef.h>

#define SETMEM_CONTROLLER_SECTIONS {n}
#define SETMEM_CONTROLLER_TS {Ts!r}

/* per section: b0, b1, b2, a1, a2 (a0 = 1) */
static const double setmem_controller_sos[SETMEM_CONTROLLER_SECTIONS][5] = {{
{rows}
}};
static const double setmem_controller_gain = {float(doc['sos_gain'])!r};

typedef struct {{
    double w[SETMEM_CONTROLLER_SECTIONS][2];
}} setmem_controller_state;

static inline void setmem_controller_init(setmem_controller_state *s)
{{
    size_t i;
    for (i = 0; i < SETMEM_CONTROLLER_SECTIONS; ++i) {{
        s->w[i][0] = 0.0;
        s->w[i][1] = 0.0;
    }}
}}

static inline double setmem_controller_step(setmem_controller_state *s, double y)
{{
    double x = y;
    size_t i;
    for (i = 0; i < SETMEM_CONTROLLER_SECTIONS; ++i) {{
        const double *c = setmem_controller_sos[i];
        double out = c[0] * x + s->w[i][0];
        s->w[i][0] = c[1] * x - c[3] * out + s->w[i][1];
        s->w[i][1] = c[2] * x - c[4] * out;
        x = out;
    }}
    return setmem_controller_gain * x;
}}

#endif /* SETMEM_CONTROLLER_H */
"""
