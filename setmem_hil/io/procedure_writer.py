"""Procedure files, the writing side: a :class:`Procedure` as TOML text.

:func:`format_procedure` writes every key explicitly; :func:`setmem_hil.io.procedure_file.
parse_procedure_text` reads the text back to an equal procedure. The run command uses it to
store programmatic procedures (``default_procedure()`` of the demo, procedures with a changed
seed or backend) in the journal, so that ``run --resume`` can rebuild them.
"""

from __future__ import annotations

import math
from dataclasses import replace  # noqa: F401  (used by the doctest)
from typing import Any, Mapping

from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import Procedure

__all__ = ["format_procedure"]


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise ProcedureError("<procedure>", "", f"cannot write a {type(v).__name__} as TOML")


def _toml_key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "_-" for c in k) else _toml_value(str(k))


def format_procedure(procedure: Procedure) -> str:
    """TOML text of a procedure, every key explicit; :func:`parse_procedure_text` reads it back equal.

    Used to store a programmatic procedure (``default_procedure()``, the demo) in a journal so
    that ``run --resume`` can rebuild it.

    Example
    -------
    >>> from setmem_hil.io.procedure import default_procedure
    >>> from setmem_hil.io.procedure_file import parse_procedure_text
    >>> p = default_procedure()
    >>> replace(parse_procedure_text(format_procedure(p)), source_text="") == p
    True
    """
    p = procedure
    out = [f"name = {_toml_value(p.name)}", f"description = {_toml_value(p.description)}", f"seed = {int(p.seed)}", ""]
    out += _backend_lines(p.backend)
    for name, inst in p.instruments.items():
        out += _instrument_lines(name, inst)
    sf = p.safety
    out += ["[safety]"] + [f"{k} = {_toml_value(float(getattr(sf, k)))}" for k in ("max_amplitude_n", "omega_min_rad_s", "omega_max_rad_s", "max_dwell_s")]
    out += [f"max_response = {_toml_value(float(sf.max_response))}"] if sf.max_response is not None else []
    out += [""]
    for m in p.prior.modes:
        out += _mode_lines(m)
    out += ["[identification]", f"gamma = {_toml_value(float(p.prior.gamma))}", f"max_partitions = {int(p.prior.max_partitions)}",
            *([f"unmodelled_bound = {_toml_value(p.unmodelled_bound)}"] if p.unmodelled_bound is not None else []), ""]
    out += ["[initial]", f"omega_rad_s = {_toml_value([float(w) for w in p.initial_omegas_rad_s])}", ""]
    out += ["[goal]", f"mu_target = {_toml_value(float(p.goal.mu_target))}", f"max_experiments = {int(p.goal.max_experiments)}", ""]
    out += _input_design_lines(p.input_design)
    w = p.weights
    out += ["[weights]"] + [f"{k} = {_toml_value([float(c) for c in getattr(w, k)])}" for k in ("w1_num", "w1_den", "w2_num", "w2_den")]
    out += [f"w2_extra_pole_rad_s = {_toml_value(float(w.w2_extra_pole_rad_s or 0.0))}", ""]
    if p.dwell_signal != "sine":
        out += ["[dwell]", f"signal = {_toml_value(p.dwell_signal)}", ""]
    if p.design_method != "robust":
        out += ["[design]", f"method = {_toml_value(p.design_method)}", ""]
    out += ["[discrepancy]", f"check_each_iteration = {_toml_value(bool(p.discrepancy_check))}", ""]
    return "\n".join(out)


def _backend_lines(b) -> list[str]:
    """``[backend]`` with its roles, ``[backend.simulation]`` (its truth file too), transport,
    faults and emulation."""
    s = b.simulation
    roles = [f"{role} = {_toml_value(getattr(b, role))}" for role in ("exciter", "force", "response") if getattr(b, role)]
    if b.responses:  # several response instruments (issue 25): the list as given, and the control output
        roles[-1:] = [f"response = {_toml_value(list(b.responses))}", f"control_output = {b.control_output}"]
    elif b.channel_outputs:  # one oscilloscope's several response channels
        roles.append(f"control_output = {b.control_output}")
    out = ["[backend]", f"kind = {_toml_value(b.kind)}", *roles, "", "[backend.simulation]",
           f"noise_profile = {_toml_value(s.noise_profile)}", f"noise_scale = {_toml_value(float(s.noise_scale))}",
           f"unmodelled_dynamics = {_toml_value(bool(s.unmodelled_dynamics))}",
           *([f"first_mode_rad_s = {_toml_value(float(s.first_mode_rad_s))}"] if s.first_mode_rad_s != 1.0 else []),
           *([f"sensors = {_toml_value([float(x) for x in s.sensors])}", f"actuator = {_toml_value(float(s.actuator))}",
              f"control_output = {int(s.control_output)}"] if (s.sensors, s.actuator) != ((1.0,), 1.0) else []),
           *([f"truth = {_toml_value(s.truth)}"] if s.truth else []), ""]
    if b.transport:
        out += ["[backend.transport]"] + [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in b.transport.items()] + [""]
    if b.faults:
        out += ["[backend.faults]"] + [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in b.faults.items()] + [""]
    if b.emulation is not None:
        out += ["[backend.emulation]", f"drive_gain_ratio = {_toml_value(float(b.emulation.drive_gain_ratio))}",
                f"noise_v_per_rthz = {_toml_value(float(b.emulation.noise_v_per_rthz))}",
                f"relock_s = {_toml_value(float(b.emulation.relock_s))}",
                f"sensors = {_toml_value([float(x) for x in b.emulation.sensors])}",
                f"actuator = {_toml_value(float(b.emulation.actuator))}"]
        if b.emulation.first_mode_rad_s != 1.0:
            out.append(f"first_mode_rad_s = {_toml_value(float(b.emulation.first_mode_rad_s))}")
        if b.emulation.damping is not None:
            out.append(f"damping = {_toml_value(float(b.emulation.damping))}")
        out.append("")
    return out


def _instrument_lines(name: str, inst) -> list[str]:
    """One ``[instruments.<name>]`` table and its channels' tables."""
    out = [f"[instruments.{_toml_key(name)}]"]
    for key in ("profile", "resource", "channel", "newton_per_volt", "max_drive_v", "load_ohms", "volt_per_unit",
                "calibration_uncertainty", "quantity", "visa_library", "iepe_current_a", "coupling"):
        value = getattr(inst, key)
        if key == "iepe_current_a" and not value:
            continue
        if value is not None and not (key == "channel" and inst.channel_sensors):
            out.append(f"{key} = {_toml_value(value)}")
    if inst.channel_roles:  # an oscilloscope (issue 26)
        roles = inst.channel_roles
        out.append(f"channels = {{ force = {roles['force'][0]}, response = {_toml_value(list(roles['response']))} }}")
    if inst.trigger_channel is not None:
        out.append(f"trigger_channel = {inst.trigger_channel}")
    if inst.channel_match is not None:
        out.append(f"channel_match = {_toml_value(inst.channel_match)}")
    out.append("")
    for ch, sensor in inst.channel_sensors.items():
        out += [f"[instruments.{_toml_key(name)}.channel.{ch}]", f"volt_per_unit = {_toml_value(sensor.volt_per_unit)}",
                f"calibration_uncertainty = {_toml_value(sensor.calibration_uncertainty)}",
                *([f"quantity = {_toml_value(sensor.quantity)}"] if sensor.quantity else []), ""]
    return out


def _mode_lines(m) -> list[str]:
    """One ``[[mode]]`` of the prior: its band, damping and residue bounds (a fixed b1 as one value)."""
    out = ["[[mode]]", f"omega_min = {_toml_value(float(m.omega_min))}", f"omega_max = {_toml_value(float(m.omega_max))}",
           f"zeta_max = {_toml_value(float(m.zeta_max))}"]
    if m.b1_fixed:
        out.append(f"b1 = {_toml_value(float(m.b1_min))}")
    else:
        out += [f"{k} = {_toml_value(float(getattr(m, k)))}" for k in ("b1_min", "b1_max") if math.isfinite(getattr(m, k))]
    out += [f"{k} = {_toml_value(float(getattr(m, k)))}" for k in ("b0_min", "b0_max") if math.isfinite(getattr(m, k))]
    return out + [""]


def _input_design_lines(d) -> list[str]:
    return ["[input_design]", f"strategy = {_toml_value(d.strategy)}", f"candidates_base = {int(d.candidates_base)}",
            f"candidates_per_iteration = {int(d.candidates_per_iteration)}",
            *(f"{key} = {_toml_value(float(getattr(d, key)))}" for key in ("candidate_omega_min_rad_s", "candidate_omega_max_rad_s")
              if getattr(d, key) is not None),
            f"exact_resolve_top = {int(d.exact_resolve_top)}",
            *([f"per_iteration = {int(d.per_iteration)}"] if d.per_iteration != 1 else []),
            *([f"ranking = {_toml_value(d.ranking)}"] if d.ranking != "thesis" else []), ""]
