"""The report's section on the closed loop measured on the real-time target: it reads the
verification's document (:mod:`setmem_hil.io.verification_file`, ``verify.json``, which ``setmem-hil
verify`` writes into the run directory as well as into its own) and lays it out."""

from __future__ import annotations

import html
from pathlib import Path

from setmem_hil.io.verification_file import VERIFICATION_FILENAME, read_verification

__all__ = ["VERIFICATION_FILENAME", "verification_section"]


def _n(x, digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def verification_section(out_dir: Path) -> str:
    head = "<h2 id='verification'>The closed loop on the real-time target</h2>"
    doc = read_verification(out_dir)
    if doc is None:
        return head + "<p>Not verified on a target yet: <code>setmem-hil verify RUN_DIR --procedure TARGET.toml --out DIR</code> " \
                      "engages the compensator in steps and checks the measured loop against the box.</p>"
    target = doc["target"]
    rows = [("verified", "yes" if doc["verified"] else "NO"), ("target", html.escape(str(target.get("identity")))),
            ("sample rate, delay", f"{_n(target['fs_hz'])} Hz, {target['delay_samples']} samples"),
            ("checksum read back", target.get("checksum_read_back") or "-"),
            ("mu-bar: continuous, implemented", f"{_n(doc.get('continuous_mu_bar'))}, {_n(doc.get('implemented_mu_bar'))}"),
            ("weighted performance: measured, claimed", f"{_n(doc['performance']['measured'])}, {_n(doc['performance']['claimed'])}")]
    first = doc.get("first_outside")
    if first:
        s = abs(complex(first["S_re"], first["S_im"]))
        rows.append(("first point outside", f"{_n(first['omega_rad_s'], 6)} rad/s at gain {first['gain']:g}: |S| {_n(s)}, predicted "
                                             f"{_n(first['predicted_abs_S_min'])}..{_n(first['predicted_abs_S_max'])}"))
    if doc.get("discrepancy"):
        d = doc["discrepancy"]
        rows.append(("what the model lacks", f"{d['effect']} " + ", ".join(f"{k} {_n(v)}" for k, v in d["parameters"].items())))
    body = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    out = head + f"<table id='table-verification'><caption>setmem-hil verify: every point against the box's prediction of S." \
                 f"</caption>{body}</table>"
    points = [(s["gain"], p) for s in doc["steps"] for p in s["points"]]
    prow = "".join(f"<tr><td>{g:g}</td><td>{_n(p['omega_rad_s'], 6)}</td><td>{_n(abs(complex(p['S_re'], p['S_im'])))}</td>"
                   f"<td>{_n(p['S_bound'], 2)}</td><td>{_n(p['predicted_abs_S_min'])}..{_n(p['predicted_abs_S_max'])}</td>"
                   f"<td>{'inside' if p['inside'] else 'OUTSIDE'}</td></tr>" for g, p in points)
    out += ("<table id='table-verification-points'><tr><th>gain</th><th>omega (rad/s)</th><th>|S|</th><th>bound</th>"
            f"<th>predicted |S|</th><th></th></tr>{prow}</table>")
    figure = Path(doc.get("figure") or "")
    if figure.is_file():
        out += f"<figure id='fig-verification'><img src='{html.escape(str(figure))}' alt='verify'><figcaption>The predicted band of " \
               "|S| per gain step and the measured points (red X: outside).</figcaption></figure>"
    return out
