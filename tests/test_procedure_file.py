"""Procedure files: every shipped procedure validates; broken ones fail naming file, table, key."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.errors import InputFormatError, ProcedureError
from setmem_hil.io.procedure import default_procedure
from setmem_hil.io.procedure_file import SCHEMA, load_procedure, parse_procedure_text
from setmem_hil.io.target_file import is_verification_procedure

REPO = Path(__file__).resolve().parents[1]
PROCEDURES = REPO / "procedures"
SHIPPED = [p for p in sorted(PROCEDURES.glob("*.toml")) if not is_verification_procedure(p.read_text())]  # those: test_verify
DEMO_TEXT = (PROCEDURES / "beam_6_3_2.toml").read_text()
SRC = "procedures/x.toml"


def test_the_shipped_set_is_complete():
    names = {p.name for p in SHIPPED}
    assert {
        "beam_6_3_2.toml", "beam_6_3_3_snr10.toml", "beam_6_3_4_resonance.toml",
        "beam_6_3_4_resonance_no_unmodelled.toml", "serial_loopback.toml", "can_virtual.toml", "modbus_loopback.toml",
    } <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_shipped_procedure_validates(path):
    p = load_procedure(path)
    assert p.source_text == path.read_text()
    assert p.source_path == str(path)
    lo, hi = p.safety.omega_min_rad_s, p.safety.omega_max_rad_s
    assert all(lo <= w <= hi for w in p.initial_omegas_rad_s)
    assert p.prior.n_modes >= 3  # the beam's three modelled modes; the two-plane beam models three pairs


def test_demo_file_equals_default_procedure():
    p = load_procedure(PROCEDURES / "beam_6_3_2.toml")
    assert dataclasses.replace(p, source_text="", source_path="") == default_procedure()


def test_thesis_cases_differ_from_the_demo_only_where_the_thesis_says():
    demo = default_procedure()
    snr = load_procedure(PROCEDURES / "beam_6_3_3_snr10.toml")
    # 6.3.3: "the same a priori information as in the previous example except for the bound on the noise"
    assert snr.backend.simulation.noise_profile == "snr10"
    assert (snr.prior, snr.initial_omegas_rad_s, snr.weights, snr.input_design) == (demo.prior, demo.initial_omegas_rad_s, demo.weights, demo.input_design)
    for fname, unmodelled in (("beam_6_3_4_resonance.toml", True), ("beam_6_3_4_resonance_no_unmodelled.toml", False)):
        p = load_procedure(PROCEDURES / fname)
        assert p.backend.simulation.noise_profile == "resonance"
        assert p.backend.simulation.unmodelled_dynamics is unmodelled
        # 6.3.4: "15 data points logarithmically spaced between .3 rad/sec and 30 rad/sec"
        w = np.array(p.initial_omegas_rad_s)
        assert w.size == 15 and w[0] == pytest.approx(0.3) and w[-1] == pytest.approx(30.0)
        np.testing.assert_allclose(np.diff(np.log(w)), np.log(100.0) / 14, rtol=1e-12)
        assert (p.prior, p.weights, p.input_design) == (demo.prior, demo.weights, demo.input_design)


def test_loopback_procedures_use_their_transport_and_are_short():
    kinds = {load_procedure(PROCEDURES / f).backend.kind for f in ("serial_loopback.toml", "can_virtual.toml", "modbus_loopback.toml")}
    assert kinds == {"serial-loopback", "can-virtual", "modbus-loopback"}
    for f in ("serial_loopback.toml", "can_virtual.toml", "modbus_loopback.toml"):
        assert load_procedure(PROCEDURES / f).goal.max_experiments <= 3


def _mutate(old: str, new: str, text: str = DEMO_TEXT) -> str:
    assert text.count(old) >= 1, old
    return text.replace(old, new, 1)


MODE2 = "omega_min = 5.41\nomega_max = 7.34"
BROKEN = [
    ("mode range", _mutate(MODE2, "omega_min = 7.3\nomega_max = 5.4"), "procedures/x.toml: [[mode]] 2: omega_min 7.3 > omega_max 5.4"),
    ("negative amplitude", _mutate("max_amplitude_n = 1.0", "max_amplitude_n = -1"), "procedures/x.toml: [safety]: max_amplitude_n -1 must be > 0"),
    ("typo in key", _mutate("max_amplitude_n = 1.0", "max_amplitude = 1.0"), "procedures/x.toml: [safety]: unknown key 'max_amplitude'; did you mean 'max_amplitude_n'?"),
    ("unknown table", DEMO_TEXT + "\n[gaol]\nmu_target = 1\n", "procedures/x.toml: top level: unknown key 'gaol'; did you mean 'goal'?"),
    ("backend kind", _mutate('kind = "sim"', 'kind = "usb"'), "procedures/x.toml: [backend]: kind 'usb' is not one of 'sim', 'serial-loopback', 'can-virtual', 'modbus-loopback'"),
    ("noise profile", _mutate('noise_profile = "fully_damped"', 'noise_profile = "pink"'), "procedures/x.toml: [backend.simulation]: noise_profile 'pink' is not one of"),
    ("unmodelled not bool", _mutate("unmodelled_dynamics = true", 'unmodelled_dynamics = "yes"'), "procedures/x.toml: [backend.simulation]: unmodelled_dynamics: expected true or false, found a string 'yes'"),
    ("transport with sim", _mutate("[safety]", "[backend.transport]\nport = 'loop://'\n\n[safety]"), "procedures/x.toml: [backend.transport]: only used by transport backends"),
    ("safety range", _mutate("omega_max_rad_s = 2000.0", "omega_max_rad_s = 0.01"), "procedures/x.toml: [safety]: omega_min_rad_s 0.05 must be < omega_max_rad_s 0.01"),
    ("initial outside safety", _mutate("0.8, 0.9, 0.95", "0.8, 0.9, 0.01"), "procedures/x.toml: [initial]: initial frequency 3 (0.01 rad/s) is outside the [safety] range [0.05, 2000] rad/s"),
    ("initial repeated", _mutate("0.8, 0.9, 0.95", "0.8, 0.9, 0.8"), "procedures/x.toml: [initial]: initial frequency 3 (0.8 rad/s) repeats frequency 1"),
    ("initial non-number", _mutate("0.8, 0.9, 0.95", "0.8, 'x', 0.95"), "procedures/x.toml: [initial]: omega_rad_s[1]: expected a number, found a string 'x'"),
    ("initial both", _mutate("[goal]", "log_spaced = { min = 0.3, max = 30.0, n = 15 }\n\n[goal]"), "procedures/x.toml: [initial]: give exactly one of omega_rad_s and log_spaced"),
    ("log spaced reversed", re.sub(r"omega_rad_s = \[[^\]]*\]", "log_spaced = { min = 30.0, max = 0.3, n = 15 }", DEMO_TEXT), "procedures/x.toml: [initial.log_spaced]: min 30 > max 0.3"),
    ("modes not ascending", _mutate("omega_min = 16.35\nomega_max = 19.81", "omega_min = 4.0\nomega_max = 4.5"), "procedures/x.toml: [[mode]] 3: modes must be in ascending frequency: omega_min 4 < omega_min 5.41 of [[mode]] 2"),
    ("zeta", _mutate("zeta_max = 0.5", "zeta_max = 0"), "procedures/x.toml: [[mode]] 1: zeta_max 0 must be in (0, 10]"),
    ("mode missing key", _mutate("omega_min = 0.884\n", ""), "procedures/x.toml: [[mode]] 1: missing key 'omega_min'"),
    ("single [mode]", DEMO_TEXT.replace("[[mode]]", "[mode]", 1).split("[[mode]]")[0] + DEMO_TEXT[DEMO_TEXT.index("[identification]"):], "procedures/x.toml: [[mode]]: found a single [mode] table; write [[mode]]"),
    ("no mode", "name = 'x'\n[initial]\nomega_rad_s = [1.0]\n", "procedures/x.toml: [[mode]]: missing"),
    ("no initial", DEMO_TEXT[: DEMO_TEXT.index("[initial]")], "procedures/x.toml: [initial]: missing"),
    ("gamma", _mutate("gamma = 1.1", "gamma = 1.0"), "procedures/x.toml: [identification]: gamma 1 must be > 1"),
    ("partitions", _mutate("max_partitions = 200", "max_partitions = 0"), "procedures/x.toml: [identification]: max_partitions 0 must be >= 1"),
    ("experiments not int", _mutate("max_experiments = 30", "max_experiments = 2.5"), "procedures/x.toml: [goal]: max_experiments: expected an integer, found a number 2.5"),
    ("mu target", _mutate("mu_target = 1.0", "mu_target = nan"), "procedures/x.toml: [goal]: mu_target: expected a finite number, found nan"),
    ("strategy", _mutate('strategy = "mu"', 'strategy = "best"'), "procedures/x.toml: [input_design]: strategy 'best' is not one of 'mu', 'log-sweep', 'random', 'max-reduction'"),
    ("candidates beyond safety", _mutate("candidate_omega_max_rad_s = 1000.0", "candidate_omega_max_rad_s = 5000.0"), "procedures/x.toml: [input_design]: candidate_omega_max_rad_s 5000 exceeds [safety] omega_max_rad_s 2000"),
    ("unstable weight", _mutate("# [weights] omitted", "[weights]\nw2_num = [1.0]\nw2_den = [1.0, -1.0]\n# x"), "procedures/x.toml: [weights]: w2_den has a pole at s = 1 (the weight must be stable)"),
    ("improper weight", _mutate("# [weights] omitted", "[weights]\nw1_num = [1.0, 2.0, 3.0]\nw1_den = [1.0, 1.0]\n# x"), "procedures/x.toml: [weights]: w1: numerator degree 2 exceeds denominator degree 1 (improper weight)"),
    ("seed negative", _mutate("seed = 1", "seed = -3"), "procedures/x.toml: top level: seed -3 must be >= 0"),
    ("seed bool", _mutate("seed = 1", "seed = true"), "procedures/x.toml: top level: seed: expected an integer, found a boolean True"),
    ("empty name", _mutate('name = "beam-6.3.2"', 'name = "  "'), "procedures/x.toml: top level: name must not be empty"),
    ("discrepancy", _mutate("check_each_iteration = false", "check_each_iteration = 1"), "procedures/x.toml: [discrepancy]: check_each_iteration: expected true or false, found an integer 1"),
    ("toml syntax", _mutate("seed = 1", "seed = = 1"), "procedures/x.toml: invalid TOML: Invalid value (at line 8, column 8)"),
    ("safety not a table", "safety = 3\n" + DEMO_TEXT.replace("[safety]", "[discrepancy.x]"), "procedures/x.toml: [safety]: expected a table, found an integer 3"),
]


@pytest.mark.parametrize("text, message", [(t, m) for _, t, m in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_procedure_fails_with_the_right_message(text, message):
    with pytest.raises(ProcedureError) as info:
        parse_procedure_text(text, SRC)
    assert str(info.value).startswith(message), str(info.value)
    assert info.value.source == SRC


FAULTY_LOOPBACK = (PROCEDURES / "serial_loopback.toml").read_text()


@pytest.mark.parametrize("insert, message", [
    ("[backend.faults]\nrate = 1.5\n", "procedures/x.toml: [backend.faults]: rate 1.5 must be <= 1"),
    ("[backend.faults]\nkinds = ['timeout', 'gremlins']\n", "procedures/x.toml: [backend.faults]: kinds: unknown fault kind 'gremlins'"),
    ("[backend.faults]\nrate = 0.1\nsed = 3\n", "procedures/x.toml: [backend.faults]: unknown key 'sed'; did you mean 'seed'?"),
    ("[backend.faults]\nkinds = ['bus_off']\n", "procedures/x.toml: [backend.faults]: kinds: unknown fault kind 'bus_off' for backend 'serial-loopback'"),
    ("[backend.faults]\nrates = { timout = 0.1 }\n", "procedures/x.toml: [backend.faults.rates]: unknown fault kind 'timout'; did you mean 'timeout'?"),
    ("[backend.faults]\nrates = { timeout = 2 }\n", "procedures/x.toml: [backend.faults.rates]: timeout: expected a probability in [0, 1], found 2"),
])
def test_broken_fault_settings(insert, message):
    text = FAULTY_LOOPBACK.replace("[safety]", insert + "\n[safety]", 1)
    with pytest.raises(ProcedureError) as info:
        parse_procedure_text(text, SRC)
    assert str(info.value).startswith(message), str(info.value)


def test_fault_settings_and_transport_options_pass_through():
    text = FAULTY_LOOPBACK.replace(
        "[safety]", "reply_timeout_s = 0.5\n\n[backend.faults]\nrate = 0.05\nkinds = ['timeout', 'corrupt']\nseed = 9\n\n[safety]", 1
    )
    p = parse_procedure_text(text, SRC)
    assert dict(p.backend.transport) == {"reply_timeout_s": 0.5}
    assert dict(p.backend.faults) == {"rate": 0.05, "kinds": ["timeout", "corrupt"], "seed": 9}
    can = (PROCEDURES / "can_virtual.toml").read_text().replace(
        "[safety]", "[backend.faults]\nkinds = ['bus_off', 'timeout']\nrates = { bus_off = 0.01 }\n\n[safety]", 1)
    assert dict(parse_procedure_text(can, SRC).backend.faults) == {"rate": 0.0, "seed": 0, "kinds": ["bus_off", "timeout"], "rates": {"bus_off": 0.01}}


def test_fault_kinds_are_the_device_simulations():
    """The validator accepts exactly the kinds the fake devices and transports know."""
    from setmem_hil.io.procedure_file import TRANSPORT_FAULT_KINDS
    from setmem_hil.sim_backends import fake_device_core, transport_faults

    for kind, extra in TRANSPORT_FAULT_KINDS.items():
        text = (PROCEDURES / f"{kind.replace('-', '_')}.toml").read_text()
        every = list(fake_device_core.FAULT_KINDS) + list(extra)
        rates = ", ".join(f"{k} = 0.01" for k in every)
        p = parse_procedure_text(text.replace("[safety]", f"[backend.faults]\nkinds = {every!r}\nrates = {{ {rates} }}\n\n[safety]", 1), SRC)
        assert p.backend.faults["kinds"] == every
        # the consumers accept what the validator let through
        core_procedure, _ = transport_faults.split_faults(p, extra)
        fake_device_core.FaultSettings.from_mapping(core_procedure.backend.faults, SRC)
    assert TRANSPORT_FAULT_KINDS["can-virtual"] == tuple(transport_faults.CAN_FAULT_KINDS)
    assert TRANSPORT_FAULT_KINDS["modbus-loopback"] == tuple(transport_faults.MODBUS_FAULT_KINDS)


def test_minimal_procedure_takes_documented_defaults():
    p = parse_procedure_text("[[mode]]\nomega_min = 1\nomega_max = 2\nzeta_max = 0.1\n[initial]\nomega_rad_s = [1.5]\n", "procedures/mini.toml")
    assert p.name == "mini"  # the file name stem
    d = default_procedure()
    assert (p.seed, p.backend, p.safety, p.goal, p.weights) == (d.seed, d.backend, d.safety, d.goal, d.weights)
    # the candidate band is derived from the weights' reference frequency (issue 18): for the
    # thesis weights it is the thesis's 0.1-1000 rad/s
    assert p.input_design.candidate_omega_min_rad_s is None
    assert p.input_design.resolved(p.weights.reference_frequency_rad_s(), p.safety) == d.input_design
    assert p.prior.modes[0].b1_fixed is False


def test_zero_extra_pole_means_none():
    p = parse_procedure_text(_mutate("# [weights] omitted", "[weights]\nw2_extra_pole_rad_s = 0\n# x"), SRC)
    assert p.weights.w2_extra_pole_rad_s is None


def test_unreadable_file(tmp_path):
    with pytest.raises(ProcedureError, match=r"missing\.toml: cannot read"):
        load_procedure(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_bytes(b"\xff\xfe name")
    with pytest.raises(ProcedureError, match="cannot read"):
        load_procedure(bad)


def test_every_schema_key_is_documented():
    doc = (REPO / "docs" / "procedures.md").read_text()
    for spec in SCHEMA:
        if spec.kind in ("table", "free-table", "tables"):
            full = f"{spec.table}.{spec.key}" if spec.table else spec.key
            heading = "[[mode]]" if full == "mode" else f"[{full}]"
            assert f"### `{heading}`" in doc, f"table {heading} has no section in docs/procedures.md"
        else:
            assert f"| `{spec.key}` |" in doc, f"{spec.table or 'top level'} {spec.key} is not documented in docs/procedures.md"


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_format_procedure_round_trips(path):
    from setmem_hil.io.procedure_file import format_procedure

    p = dataclasses.replace(load_procedure(path), source_text="", source_path="")
    q = parse_procedure_text(format_procedure(p), "<written>")
    assert dataclasses.replace(q, source_text="") == p


def test_format_procedure_round_trips_free_form_options():
    from setmem_hil.io.procedure_file import format_procedure

    text = FAULTY_LOOPBACK.replace("[safety]", 'max_attempts = 3\nlearn_poles = true\nbackoff_s = 0.0\n\n[backend.faults]\nrate = 0.1\n\n[safety]', 1)
    p = dataclasses.replace(parse_procedure_text(text, SRC), source_text="")
    q = dataclasses.replace(parse_procedure_text(format_procedure(p), SRC), source_text="")
    assert q == p and q.backend.transport == {"max_attempts": 3, "learn_poles": True, "backoff_s": 0.0}


# --- issue 12: every key of every table is known; a typo names the key (and the likely one) ---
TYPO_CASES = [
    ("serial_loopback.toml", "[backend.transport]", "reply_timout_s = 0.5", "reply_timout_s", "reply_timeout_s"),
    ("can_virtual.toml", "[backend.transport]", "gap_timout_s = 0.5", "gap_timout_s", "gap_timeout_s"),
    ("modbus_loopback.toml", "[backend.transport]", "framr = 'rtu'", "framr", "framer"),
    ("serial_loopback.toml", "[backend.transport]", "framer = 'rtu'", "framer", None),  # Modbus only
    ("beam_6_3_2.toml", "[safety]", "max_amplitud_n = 1.0", "max_amplitud_n", "max_amplitude_n"),
    ("beam_6_3_2.toml", "[goal]", "mu_targt = 1.0", "mu_targt", "mu_target"),
    ("beam_6_3_2.toml", "[input_design]", "stratgy = 'mu'", "stratgy", "strategy"),
    ("beam_6_3_2.toml", "[backend.simulation]", "noise_scal = 1.0", "noise_scal", "noise_scale"),
    ("beam_6_3_2.toml", "[discrepancy]", "check_each_iteraton = true", "check_each_iteraton", "check_each_iteration"),
    ("beam_6_3_2.toml", "[[mode]]", "zeta_mx = 0.5", "zeta_mx", "zeta_max"),
]


@pytest.mark.parametrize("name, table, line, key, hint", TYPO_CASES)
def test_misspelt_key_anywhere_fails_run_check_naming_it(tmp_path, capsys, name, table, line, key, hint):
    from setmem_hil.cli.main import main

    text = (PROCEDURES / name).read_text()
    if table not in text:
        text += f"\n{table}\n"
    text = text.replace(table, f"{table}\n{line}", 1)
    path = tmp_path / name
    path.write_text(text)
    assert main(["run", "--check", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"unknown key '{key}'" in err and str(path) in err and len(err.strip().splitlines()) == 1
    if hint:
        assert f"did you mean '{hint}'" in err


@pytest.mark.parametrize("line, problem", [
    ("reply_timeout_s = -5", "reply_timeout_s -5 must be >= 0.001"),
    ("max_attempts = 0", "max_attempts 0 must be >= 1"),
    ("backoff_s = 'fast'", "backoff_s: expected a number"),
    ("learn_poles = 1", "learn_poles: expected true or false"),
])
def test_transport_values_are_checked_by_run_check(tmp_path, capsys, line, problem):
    from setmem_hil.cli.main import main

    for name in ("serial_loopback.toml", "can_virtual.toml", "modbus_loopback.toml"):  # the same rule everywhere
        text = (PROCEDURES / name).read_text().replace("[backend.transport]", f"[backend.transport]\n{line}", 1)
        path = tmp_path / name
        path.write_text(text)
        assert main(["run", "--check", str(path)]) == 2
        assert problem in capsys.readouterr().err


def test_packaged_demo_procedure_is_the_shipped_file_and_the_thesis_default():
    """The demo stores the shipped file's text (comments kept); it must not drift from the repo copy."""
    import dataclasses as dc

    from setmem_hil.cli.commands.demo import packaged_demo_procedure

    packaged = Path(__file__).resolve().parents[1] / "setmem_hil" / "procedures" / "beam_6_3_2.toml"
    assert packaged.read_bytes() == (PROCEDURES / "beam_6_3_2.toml").read_bytes()
    p = packaged_demo_procedure()
    strip = lambda q: dc.replace(q, source_text="", source_path="", description="")  # noqa: E731
    assert strip(p) == strip(default_procedure())
    assert "#" in p.source_text  # the comments are what the run stores


def test_missing_safety_table_is_an_error_for_a_rig_and_a_default_for_the_simulation():
    serial = (PROCEDURES / "serial_loopback.toml").read_text()
    start = serial.index("[safety]")
    end = serial.index("\n[", start + 1)
    without = serial[:start] + serial[end + 1:]
    with pytest.raises(ProcedureError, match=r"drives an exciter: give a \[safety\] table"):
        parse_procedure_text(without, SRC)
    beam = (PROCEDURES / "beam_6_3_2.toml").read_text()
    start = beam.index("[safety]")
    end = beam.index("\n[", start + 1)
    assert parse_procedure_text(beam[:start] + beam[end + 1:], SRC).safety == default_procedure().safety


def test_frequencies_in_hz_are_the_same_procedure_as_in_rad_s():
    """Issue 18: every frequency key has an _hz twin (value x 2 pi); both at once is an error."""
    import math
    import re

    text = (PROCEDURES / "beam_6_3_2.toml").read_text()
    ref = parse_procedure_text(text, SRC)

    def to_hz(match):  # omega_min = 0.884 -> omega_min_hz = 0.884 / (2 pi), and lists alike
        key, value = match.group(1), match.group(2)
        values = [float(v) / (2 * math.pi) for v in re.findall(r"[-+0-9.eE]+", value)]
        body = f"[{', '.join(repr(v) for v in values)}]" if value.strip().startswith("[") else repr(values[0])
        stem = key[: -len("_rad_s")] if key.endswith("_rad_s") else key
        return f"{stem}_hz = {body}"

    hz = re.sub(r"^(omega_min|omega_max|omega_min_rad_s|omega_max_rad_s|omega_rad_s|candidate_omega_min_rad_s|candidate_omega_max_rad_s)"
                r" = (\[[^\]]*\]|[-+0-9.eE]+)", to_hz, text, flags=re.M)
    assert "omega_min_hz" in hz and "omega_hz = [" in hz
    p = parse_procedure_text(hz, SRC)
    assert p.prior.modes[0].omega_min == pytest.approx(ref.prior.modes[0].omega_min, rel=1e-15)
    np.testing.assert_allclose(p.initial_omegas_rad_s, ref.initial_omegas_rad_s, rtol=1e-15)
    assert p.safety.omega_max_rad_s == pytest.approx(ref.safety.omega_max_rad_s, rel=1e-15)
    with pytest.raises(InputFormatError, match="not both"):
        parse_procedure_text(text.replace("omega_min = 0.884", "omega_min = 0.884\nomega_min_hz = 0.14", 1), SRC)


@pytest.mark.parametrize("change, where, message", [
    (("fs_hz = 1000.0", 'fs_hz = "fast"'), "[target]", "fs_hz: expected a number, found a string 'fast'"),
    (("delay_samples = 1", "delay_samples = -1"), "[target]", "delay_samples -1 must be >= 0"),
    (("fs_hz = 1000.0", "fs_hz = 0"), "[target]", "fs_hz 0 must be > 0"),
    (("[target.emulation]\n", "[target.emulation]\ndac_gian = 1.3\n"), "[target.emulation]", "unknown key 'dac_gian'; did you mean 'dac_gain'?"),
    (("periods = 20", "periods = 2.5"), "[verify]", "periods: expected an integer, found a number 2.5"),
    (("kind = \"emulated\"", ""), "[target]", "missing key 'kind' (the target)"),
])
def test_a_verification_procedure_is_checked_by_the_procedures_own_reader(change, where, message):
    """TARGET.toml and the campaign's procedure are read by one checked-table reader
    (setmem_hil.io.toml_table): a bad value is named the same way in both, with its table."""
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.target_file import parse_target_text

    text = (REPO / "procedures" / "closed_loop_emulated.toml").read_text()
    assert change[0] in text
    with pytest.raises(ProcedureError) as err:
        parse_target_text(text.replace(change[0], change[1], 1), "t.toml")
    assert message in str(err.value) and where in str(err.value) and "t.toml" in str(err.value), str(err.value)
