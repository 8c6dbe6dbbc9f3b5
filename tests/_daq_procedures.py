"""A generator + NI-DAQ procedure's text, shared by the DAQ tests (one place to keep it valid)."""

from __future__ import annotations


def daq_procedure_text(generator_resource: str, *, force: str = "daq_force", response: str = "daq_response",
                       force_keys: str = "", response_keys: str = "") -> str:
    """33500B on ``generator_resource``; force on ``Dev1/ai0`` (22.5 mV/N), response on ``Dev1/ai1``
    (4 mV per unit); ``*_keys``: more lines for each channel's table."""
    return f'''
name = "daq-rig"
[backend]
kind = "instruments"
exciter = "fgen"
force = "{force}"
response = "{response}"
[instruments.fgen]
profile = "keysight-33500b"
resource = "{generator_resource}"
newton_per_volt = 4.0
max_drive_v = 2.5
[instruments.{force}]
profile = "ni-daqmx"
resource = "Dev1/ai0"
volt_per_unit = 0.0225
{force_keys}
[instruments.{response}]
profile = "ni-daqmx"
resource = "Dev1/ai1"
volt_per_unit = 0.004
{response_keys}
[safety]
max_amplitude_n = 1.0
omega_min_rad_s = 0.05
omega_max_rad_s = 2000.0
max_dwell_s = 3600.0
[[mode]]
omega_min = 0.884
omega_max = 1.125
zeta_max = 0.5
b1 = 0.0
[initial]
omega_rad_s = [3.0]
'''
