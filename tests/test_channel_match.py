"""Issue 26: the oscilloscope's channel match (``setmem-hil calibrate-channels``).

Truths are independent of the code under test: synthetic gains and adversarial errors for the
solver, simulated 8-bit quantization for the amplitude bound, and the emulated scope's own gain
table (``ScopeEmulator.gain``: a part per channel and a part per V/div setting, unknown to the
drivers) for the measurement through the emulated 33500B and DS1104Z.
"""

from __future__ import annotations

import datetime
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.estimation.channel_match import MatchRecord, amplitude_error_bound, fit_amplitude, solve_channel_match
from setmem_hil.drivers.instruments.scope_channel_match import match_plan

REPO = Path(__file__).resolve().parents[1]
SCOPE_TEXT = (REPO / "procedures" / "instruments_scope_emulated.toml").read_text()
MATCH_NAME = "instruments_scope_emulated.channel-match.json"


def _records(true_gain, plan, errors):
    """The plan's records with amplitudes ``G(c, s) V (1 + e)``, ``V`` the plan's amplitude."""
    records = []
    for k, (scales, amplitude) in enumerate(plan):
        amps = {c: true_gain[(c, s)] * amplitude * (1 + errors[k][c]) for c, s in scales.items()}
        records.append(MatchRecord(scales, amps, {c: abs(errors[k][c]) / 0.999 + 1e-12 for c in scales}))
    return records


def test_the_solved_gains_hold_the_truth_under_worst_case_errors():
    rng = np.random.default_rng(4)
    scales = (1e-3, 2e-3, 5e-3, 1e-2, 2e-2, 5e-2)
    channels = (1, 2, 3)
    plan = match_plan(scales, channels, 1, 4.0, (1e-4, 10.0))
    true_gain = {(c, s): 1 + rng.uniform(-0.03, 0.03) for c in channels for s in scales}
    reference = (1, 1e-2)
    exact = solve_channel_match(_records(true_gain, plan, [{c: 0.0 for c in channels}] * len(plan)), reference)
    for g in exact:  # no error: the ratios exactly, bound 0
        assert g.gain == pytest.approx(true_gain[(g.channel, g.scale_v)] / true_gain[reference], rel=1e-12)
    for trial in range(20):  # errors at their bound's edge with random signs: the truth stays inside
        errors = [{c: rng.choice([-1, 1]) * rng.uniform(0.5e-3, 2e-3) for c in channels} for _ in plan]
        for g in solve_channel_match(_records(true_gain, plan, errors), reference):
            truth = true_gain[(g.channel, g.scale_v)] / true_gain[reference]
            assert abs(truth / g.gain - 1) <= g.bound * (1 + 1e-9), (trial, g)
            assert g.bound < 0.05


def test_scales_not_linked_to_the_reference_are_refused():
    records = [MatchRecord({1: 0.01, 2: 0.01}, {1: 1.0, 2: 1.0}, {1: 1e-3, 2: 1e-3}),
               MatchRecord({1: 0.1, 2: 0.1}, {1: 1.0, 2: 1.0}, {1: 1e-3, 2: 1e-3})]
    with pytest.raises(ValueError, match="not linked"):
        solve_channel_match(records, (1, 0.01))


@pytest.mark.parametrize("noise_codes", [0.0, 0.3, 0.6])
def test_the_amplitude_bound_holds_a_quantized_noisy_sine(noise_codes):
    """An 8-bit ADC, 25 codes a division, the sine at 3.2 divisions: the fitted amplitude is
    within its bound of the true one at every phase and offset tried (the bound counts a code as
    1.5 screens / 256 as channel_errors does: never smaller than the true code)."""
    rng = np.random.default_rng(8)
    code = 1.0 / 25.0
    f, n = 1000.0, 20000
    t = np.arange(n) / 50e3
    worst = 0.0
    for _ in range(40):
        amplitude = 3.2 * rng.uniform(0.9, 1.0)
        v = amplitude * np.sin(2 * math.pi * f * t + rng.uniform(0, 2 * math.pi)) + rng.uniform(-0.5, 0.5) * code
        v = v + noise_codes * code * rng.standard_normal(n)
        quantized = np.round(v / code) * code
        fitted, _ = fit_amplitude(t, quantized, f)
        noise = float(np.std(np.round(noise_codes * code * rng.standard_normal(n) / code) * code))  # measured with nothing connected
        bound = amplitude_error_bound(fitted, n, noise, 1.5 * 8 / 256)
        worst = max(worst, abs(fitted - amplitude) / (bound * fitted))
    assert worst <= 1.0


@pytest.mark.slow
def test_the_emulated_scopes_match_holds_its_true_gain_at_every_scale():
    from setmem_hil.drivers.instruments.instrument_set import calibrate_scope_channels
    from setmem_hil.io.procedure_file import parse_procedure_text
    from setmem_hil.loopback.instrument_emulation import start_emulators

    procedure = parse_procedure_text(SCOPE_TEXT, "scope.toml")
    wired, bench, servers = start_emulators(procedure, 11, tee=True)
    scope = next(s.emulator for s in servers if hasattr(s.emulator, "gain"))
    match = calibrate_scope_channels(wired, clock=bench.clock, owned=tuple(servers))
    assert not bench.output_on
    assert match.identity.startswith("RIGOL TECHNOLOGIES,DS1104Z,") and match.reference == (1, 0.01)

    def true_gain(channel, scale):
        scope.channel[channel]["SCAL"] = scale
        return scope.gain(channel)

    reference = true_gain(1, 0.01)
    assert len(match.gains) >= 4 * 10  # every channel at every scale 2.5 V of drive can fill
    spread = []
    for g in match.gains:
        truth = true_gain(g.channel, g.scale_v) / reference
        assert abs(truth / g.gain - 1) <= g.bound, g
        spread.append(abs(truth - 1))
    assert max(spread) > 0.01  # the emulated gains do differ: the test could fail
    assert max(g.bound for g in match.gains) < 0.03


def _write(tmp_path, text=SCOPE_TEXT):
    path = tmp_path / "scope.toml"
    path.write_text(text)
    return path


def test_a_real_rig_without_its_channel_match_is_exit_2_naming_the_key(tmp_path, capsys):
    real = re.sub(r"\[backend.emulation\]\n(?:[a-z_]+ = [^\n]*\n)+", "", SCOPE_TEXT)
    from setmem_hil.io.procedure_file import parse_procedure_text

    assert parse_procedure_text(real, "real.toml").backend.emulation is None
    path = _write(tmp_path, real)
    for args in (["run", str(path), "--out", str(tmp_path / "run"), "--quiet"], ["run", "--check", str(path)]):
        code = main(args)
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2
        assert len(err) == 1 and "key 'channel_match'" in err[0] and "calibrate-channels" in err[0], err
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_match_from_another_scope_is_exit_4_naming_it(tmp_path, capsys):
    path = _write(tmp_path)
    assert main(["calibrate-channels", str(path), "--seed", "5"]) == 0  # another emulated unit
    capsys.readouterr()
    code = main(["run", str(path), "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 4
    assert len(err) == 1 and "channel match" in err[0] and "DS1ZA123400005" in err[0] and "calibrate-channels" in err[0], err


@pytest.mark.slow
def test_an_old_or_malformed_match_is_exit_2_naming_it(tmp_path, capsys):
    path = _write(tmp_path)
    assert main(["calibrate-channels", str(path)]) == 0
    match_file = tmp_path / MATCH_NAME
    doc = json.loads(match_file.read_text())
    assert doc["kind"] == "setmem-hil channel match" and doc["version"] == 1 and doc["reference"]["channel"] == 1
    assert {"channel", "scale_v", "gain", "bound"} <= set(doc["gains"][0])
    assert main(["run", "--check", str(path)]) == 0  # fresh: accepted
    doc["utc"] = (datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(hours=30)).isoformat()
    match_file.write_text(json.dumps(doc))
    assert main(["run", "--check", str(path)]) == 2
    capsys.readouterr()
    code = main(["run", str(path), "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "30 h ago" in err[0], err
    match_file.write_text('{"kind": "setmem-hil channel match", "version": 1, "gains": 3}')
    code = main(["run", str(path), "--out", str(tmp_path / "run2"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and MATCH_NAME in err[0], err


def test_channel_match_round_trips_and_belongs_to_an_oscilloscope():
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.procedure_file import format_procedure, parse_procedure_text

    p = parse_procedure_text(SCOPE_TEXT, "scope.toml")
    assert p.instruments["scope"].channel_match == MATCH_NAME
    assert parse_procedure_text(format_procedure(p), "again.toml").instruments["scope"].channel_match == MATCH_NAME
    lockins = (REPO / "procedures" / "instruments_emulated.toml").read_text()
    text = re.sub(r"(\[instruments\.\w+\]\nprofile = \"srs-sr8\d+\")", r'\1\nchannel_match = "m.json"', lockins, count=1)
    assert text != lockins
    with pytest.raises(ProcedureError, match=r"key 'channel_match'.*only an oscilloscope"):
        parse_procedure_text(text, "lockins.toml")


def _hand_written_match(tmp_path, scope_idn: str, hours_old: float = 0.0, **changes) -> Path:
    """A match file written from the documented contract (docs/procedures.md), not by the code
    under test: the fast tier's check of what a run does with it."""
    utc = datetime.datetime.now(datetime.timezone.utc) - datetime.timedelta(hours=hours_old)
    doc = {"kind": "setmem-hil channel match", "version": 1, "scope": scope_idn, "frequency_hz": 1000.0,
           "utc": utc.isoformat(), "reference": {"channel": 1, "scale_v": 0.01},
           "gains": [{"channel": c, "scale_v": s, "gain": 1.0, "bound": 1e-3} for c in (1, 2, 3, 4)
                     for s in (1e-3, 2e-3, 5e-3, 1e-2, 2e-2, 5e-2, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)]}
    doc.update(changes)
    path = tmp_path / MATCH_NAME
    path.write_text(json.dumps(doc))
    return path


def test_a_hand_written_match_of_another_scope_is_exit_4_and_a_stale_or_malformed_one_exit_2(tmp_path, capsys):
    """The contract of the slow tier's two tests above, on match files written by hand: another
    unit's serial is exit 4 naming it; older than 24 h, or a `gains` that is no list, exit 2."""
    path = _write(tmp_path)
    _hand_written_match(tmp_path, "RIGOL TECHNOLOGIES,DS1104Z,DS1ZA123400077,00.04.04.SP4")
    code = main(["run", str(path), "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 4
    assert len(err) == 1 and "channel match" in err[0] and "DS1ZA123400077" in err[0] and "calibrate-channels" in err[0], err
    _hand_written_match(tmp_path, "RIGOL TECHNOLOGIES,DS1104Z,DS1ZA123456789,00.04.04.SP4", hours_old=30)
    assert main(["run", "--check", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "30 h ago" in err[0], err
    _hand_written_match(tmp_path, "RIGOL TECHNOLOGIES,DS1104Z,DS1ZA123456789,00.04.04.SP4", gains=3)
    code = main(["run", str(path), "--out", str(tmp_path / "run2"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and MATCH_NAME in err[0], err
