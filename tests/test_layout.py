"""Packaging: drivers/, sim_backends/ and firmware/ are importable only inside the setmem_hil namespace,
and the firmware's C sources are package data (an installed copy can build the emulated target)."""

import importlib.util


def test_drivers_and_sim_backends_are_not_top_level_names():
    assert importlib.util.find_spec("drivers") is None
    assert importlib.util.find_spec("sim_backends") is None
    assert importlib.util.find_spec("firmware") is None


def test_mapped_subpackages_import():
    import setmem_hil.drivers.protocols  # noqa: F401
    import setmem_hil.sim_backends.beam  # noqa: F401
    from setmem_hil.firmware import BOARD_SOURCES, SOURCE_DIR
    from setmem_hil.sim_backends.firmware_core import SIL_SOURCE

    assert all((SOURCE_DIR / name).is_file() for name in (*BOARD_SOURCES, "hal.h", "host/hal_host.c")) and SIL_SOURCE.is_file()
