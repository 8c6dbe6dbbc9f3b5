"""Packaging: drivers/ and sim_backends/ are importable only inside the setmem_hil namespace."""

import importlib.util


def test_drivers_and_sim_backends_are_not_top_level_names():
    assert importlib.util.find_spec("drivers") is None
    assert importlib.util.find_spec("sim_backends") is None


def test_mapped_subpackages_import():
    import setmem_hil.drivers.protocols  # noqa: F401
    import setmem_hil.sim_backends.beam  # noqa: F401
