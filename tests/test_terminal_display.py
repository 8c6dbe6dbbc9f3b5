"""Issue 17: the terminal display at 80 and 120 columns, as a technician sees it (rich recording console)."""

from __future__ import annotations

import dataclasses
import math

import pytest
from rich.console import Console

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.cli.commands.campaign import print_iteration_table
from setmem_hil.cli.progress import CampaignProgress
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure import Goal, default_procedure


@pytest.fixture(scope="module")
def short_campaign_events():
    """The events of a 2-experiment 6.3.2 campaign, recorded once and replayed into each display."""
    procedure = dataclasses.replace(default_procedure(), goal=Goal(mu_target=1.0, max_experiments=2))
    events = []
    with open_experiment(procedure, procedure.seed) as experiment:
        summary = run_campaign(procedure, experiment, progress=lambda event, **info: events.append((event, info)))
    return events, summary


@pytest.mark.slow
@pytest.mark.parametrize("width", [80, 120])
def test_live_display_fits_the_terminal_and_ends_without_a_stale_choice(short_campaign_events, width):
    """Every frame of the live display (rendered at the terminal's width after each event) shows
    whole words, and the last frame names no next frequency once the run is over."""
    events, _ = short_campaign_events
    console = Console(record=True, width=width, force_terminal=True, color_system=None)
    frames = []
    with CampaignProgress(console, live=True) as display:
        for event, info in events:
            display(event, **info)
            snap = Console(record=True, width=width, color_system=None)
            snap.print(display._progress.get_renderable())
            frames.append([line.rstrip() for line in snap.export_text().splitlines() if line.strip()])
    for frame in frames:
        assert all(len(line) <= width for line in frame)
        assert not any("…" in line for line in frame), frame  # nothing cut off
    # the choice as the status line must show it, in both units (4 significant figures; Hz = w/2pi)
    chosen = [float(info["next_omega"]) for event, info in events if event == "chosen"]
    assert chosen, "the 2-experiment campaign chose no frequency"
    expected = f"next {chosen[0]:.4g} rad/s ({chosen[0] / (2 * math.pi):.4g} Hz)"
    assert any(expected in line for frame in frames for line in frame), expected
    assert not any("next " in line for line in frames[-1]), frames[-1]
    printed = console.export_text()
    assert "iteration 1: 15 points, mu-bar peak" in printed and "finished:" in printed


@pytest.mark.slow
@pytest.mark.parametrize("width", [80, 120])
def test_iteration_table_rounds_mu_bar(short_campaign_events, width):
    _, summary = short_campaign_events
    console = Console(record=True, width=width, color_system=None)
    print_iteration_table(summary.to_document(), console)
    text = console.export_text()
    assert f"final mu-bar {summary.final_mu_peak:.4f}," in text
    assert repr(summary.final_mu_peak) not in text
    assert all(len(line.rstrip()) <= width for line in text.splitlines())


@pytest.mark.slow
def test_a_several_sensor_campaign_prints_the_shared_poles_and_every_output_residues():
    """Issue 25: each iteration's terminal lines name every sensor with its b0 intervals; the
    truth (the cantilever's residues at each sensor, beam theory) lies inside what is printed."""
    import re

    from setmem_hil.sim_backends.beam import beam_parameters_at

    p = default_procedure()
    sim = dataclasses.replace(p.backend.simulation, sensors=(1.0, 0.4, 0.7))
    procedure = dataclasses.replace(p, backend=dataclasses.replace(p.backend, simulation=sim), goal=Goal(mu_target=1.0, max_experiments=1))
    console = Console(record=True, width=120, color_system=None)
    with CampaignProgress(console, live=False) as display, open_experiment(procedure, procedure.seed) as experiment:
        run_campaign(procedure, experiment, progress=display)
    lines = console.export_text().splitlines()
    assert any(line.startswith("  shared natural frequencies (rad/s): [") for line in lines)
    for x, name in ((1.0, "x=1 (control)"), (0.4, "x=0.4"), (0.7, "x=0.7")):
        last = [line for line in lines if line.startswith(f"  {name}: b0 ")][-1]
        intervals = [tuple(map(float, pair)) for pair in re.findall(r"\[([^,\]]+), ([^\]]+)\]", last)]
        truth = beam_parameters_at(x, n_modes=3).values[:, 3]
        assert len(intervals) == 3
        for (lo, hi), b0 in zip(intervals, truth):
            assert lo - 5e-3 * abs(lo) <= b0 <= hi + 5e-3 * abs(hi)  # printed to 3 significant digits
