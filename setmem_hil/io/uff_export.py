"""A run's measured FRF as UFF dataset 58, the field's exchange format (issue 39, item 4).

One record per output (the control output first), through pyuff: function type 4 (FRF),
abscissa in Hz (specific data type 18), ordinate displacement (8) over force (13): the points are
receptances, as the campaign identifies them. Binary 58 (``58b``) with complex double ordinates
and an uneven abscissa: every frequency and response comes back bit for bit. UFF 58 has no field
for an error bound: the bounds are in ``data.csv`` (``export --csv``); reading the file back
(``identify --data FILE.uff``) asks for ``--bound-rel``/``--bound-abs`` as for any UFF file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.io.journal import read_snapshot
from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["export_uff"]

UFF_FRF, HZ, DISPLACEMENT, FORCE = 4, 18, 8, 13
COMPLEX_DOUBLE = 6


def export_uff(run_dir: str | os.PathLike, path: str | os.PathLike, names: tuple[str, ...] = ()) -> Path:
    """Write ``run_dir``'s measurements to ``path`` (replaced if it exists); returns the path.
    ``names``: the outputs' names in measurement order (the record's ID line 3)."""
    import pyuff

    snap = read_snapshot(run_dir)
    if not snap.measurements:
        raise InputFormatError(str(run_dir), "", "the run has no measurement yet: nothing to write")
    out = Path(path)
    tmp = out.with_name(out.name + ".part")
    tmp.unlink(missing_ok=True)
    n_outputs = 1 + len(snap.measurements[0].others)
    writer = pyuff.UFF(str(tmp))
    for k in range(n_outputs):
        data = FrequencyData.from_measurements(snap.measurements, output=k).sorted_by_frequency()
        name = names[k] if k < len(names) else f"output {k + 1}"
        writer.write_sets(_record(data, k, name, str(snap.info.get("procedure_name", ""))), mode="add")
    os.replace(tmp, out)
    return out


def _record(data: FrequencyData, k: int, output: str, run_name: str) -> dict:
    import pyuff

    f_hz = data.omega_rad_s / (2 * np.pi)
    return pyuff.prepare_58(
        binary=1, func_type=UFF_FRF, ver_num=0, load_case_id=0,
        id1="setmem-hil export"[:80], id2=run_name[:80], id3=output[:80],
        id4="receptance; bounds: data.csv (UFF 58 has no error field)", id5="",
        rsp_ent_name=output[:10] or "response", rsp_node=k + 1, rsp_dir=3, ref_ent_name="force", ref_node=0, ref_dir=3,
        ord_data_type=COMPLEX_DOUBLE, num_pts=int(f_hz.size), abscissa_spacing=0, z_axis_value=0.0,
        abscissa_spec_data_type=HZ, abscissa_axis_units_lab="Hz", ordinate_spec_data_type=DISPLACEMENT,
        ordinate_axis_units_lab="response unit", orddenom_spec_data_type=FORCE, orddenom_axis_units_lab="force unit",
        data=np.asarray(data.response, dtype=complex), x=np.asarray(f_hz, dtype=float))
