"""Issue 40 item 5: a technician following the README never meets a missing package.

The README's first command installs the core dependencies only; every shipped procedure the
technician section uses must then find what drives its instruments, and ``run --check`` must name
a missing driver package (with the command that installs it) instead of saying OK and letting the
run stop at its first connection.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

from setmem_hil.cli.main import main
from setmem_hil.drivers.instruments.instrument_set import DRIVER_PACKAGES, check_instruments
from setmem_hil.io.procedure_file import load_procedure

import importlib.util as _importlib_util  # noqa: E402

_spec = _importlib_util.spec_from_file_location("_daq_procedures", Path(__file__).with_name("_daq_procedures.py"))
_daq_procedures = _importlib_util.module_from_spec(_spec)
_spec.loader.exec_module(_daq_procedures)
daq_procedure_text = _daq_procedures.daq_procedure_text

REPO = Path(__file__).resolve().parents[1]
TECHNICIAN_PROCEDURES = sorted(set(re.findall(r"procedures/(\w+\.toml)", (REPO / "README.md").read_text())))


def _core_requirements() -> set[str]:
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    return {re.split(r"[<>=~!;\[ ]", d, maxsplit=1)[0].lower().replace("_", "-") for d in deps}


@pytest.mark.parametrize("name", [n for n in TECHNICIAN_PROCEDURES if "instruments" in n])
def test_the_readmes_instrument_procedures_need_only_core_dependencies(name):
    """What the first command installs (pyproject's core dependencies) drives every instrument
    of the procedures the README's technician section runs: PyVISA and pyvisa-py included."""
    procedure = load_procedure(REPO / "procedures" / name)
    core = _core_requirements()
    distributions = {"pyvisa": "pyvisa", "pyvisa_py": "pyvisa-py", "can": "python-can", "pymodbus": "pymodbus",
                     "cantools": "cantools", "nidaqmx": "nidaqmx", "canopen": "canopen"}
    for settings, profile, _ in check_instruments(procedure).values():
        modules = [m for m, _ in DRIVER_PACKAGES.get(profile.kind, ())]
        if profile.kind.startswith("scpi-"):
            modules.append("pyvisa_py")
        for module in modules:
            assert distributions[module] in core, f"{name}: {settings.name} needs {module}, not in the core dependencies"


def test_run_check_names_a_missing_driver_package_and_how_to_install_it(monkeypatch, capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pyvisa" else real(name, *a))
    code = main(["run", "--check", str(REPO / "procedures" / "instruments_emulated.toml")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "[instruments.fgen] key 'profile'" in err[0] and "'pyvisa'" in err[0] \
        and "pip install 'setmem-hil[instruments]'" in err[0], err


DAQ_PROCEDURE = daq_procedure_text("TCPIP::192.168.1.20::5025::SOCKET")


def test_run_check_names_a_missing_nidaqmx_for_a_daq_procedure(monkeypatch, capsys, tmp_path):
    (tmp_path / "daq.toml").write_text(DAQ_PROCEDURE)
    assert main(["run", "--check", str(tmp_path / "daq.toml")]) == 0  # nidaqmx is in [test]
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "nidaqmx" else real(name, *a))
    capsys.readouterr()
    assert main(["run", "--check", str(tmp_path / "daq.toml")]) == 2
    err = capsys.readouterr().err
    assert "[instruments.daq_force] key 'profile'" in err and "'nidaqmx'" in err and "pip install 'setmem-hil[daq]'" in err
