"""Live progress of a campaign on the terminal (rich), from ``run_campaign``'s progress events.

Events (see :func:`setmem_hil.campaign.runner.run_campaign`): ``"measure"`` (index, total, omega_rad_s,
replayed) just before a dwell starts (or a stored measurement is replayed), ``"iteration"``
(k, n_points, mu_peak, mu_peak_omega, safeguard, design, floor_modes) after each identification and analysis
(Algorithm 5.1 steps 2-3), ``"chosen"`` (k, next_omega) after the input design (steps 5-7),
``"finished"`` (summary).

On a terminal two bars show the measurements done (with the iteration, the current peak of
mu-bar and the next frequency) and the dwell under way (frequency; elapsed against the dwell's
length when the experiment can tell it, else a pulsing bar); iteration results are printed as
lines above them. Elsewhere (a
pipe, a log file, CI) the same information is printed as plain lines, one per event.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Callable

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.text import Text

__all__ = ["CampaignProgress", "format_frequency", "format_mu", "terminal_display"]


class _CampaignBars(Progress):
    """The measurement and dwell bars, and below them the campaign status as a line of its own
    (wrapped, never cut, on a narrow terminal)."""

    status_text = ""

    def get_renderables(self):
        yield self.make_tasks_table(self.tasks)
        if self.status_text:
            yield Text(self.status_text, overflow="fold")


def format_frequency(omega_rad_s: float) -> str:
    """A frequency in both units a lab uses: ``6.246 rad/s (0.9941 Hz)``."""
    if not math.isfinite(omega_rad_s):
        return "-"
    return f"{omega_rad_s:.4g} rad/s ({omega_rad_s / (2 * math.pi):.4g} Hz)"


def format_duration(seconds: float) -> str:
    """``734 s`` as ``12 min 14 s`` (rig time)."""
    if not math.isfinite(seconds):
        return "?"
    if seconds < 120:
        return f"{seconds:.0f} s"
    minutes, rest = divmod(int(round(seconds)), 60)
    return f"{minutes} min {rest} s" if minutes < 120 else f"{minutes // 60} h {minutes % 60} min"


def format_mu(mu: float) -> str:
    """mu-bar for humans: ``inf`` when the nominal loop is unstable."""
    return "inf (nominal loop unstable)" if not math.isfinite(mu) else f"{mu:.4f}"


class CampaignProgress:
    """Callable ``progress(event, **info)`` that renders a campaign; a context manager.

    Parameters
    ----------
    console : rich.console.Console, optional
        Where to draw (default: stdout).
    planned_dwell_s : callable, optional
        ``planned_dwell_s(omega_rad_s) -> float`` (seconds) for the dwell line, e.g. from
        :meth:`setmem_hil.drivers.sine_dwell.SineDwellExperiment.plan`.
    on_event : callable, optional
        Called with every event after rendering (the run command uses it to log device
        counters to the journal).
    live : bool, optional
        Draw a live bar (default: when the console is a terminal).
    """

    def __init__(
        self,
        console: Console | None = None,
        *,
        planned_dwell_s: Callable[[float], float] | None = None,
        on_event: Callable[..., None] | None = None,
        live: bool | None = None,
    ):
        self.console = console or Console(soft_wrap=True)
        self.planned_dwell_s = planned_dwell_s
        self.on_event = on_event
        self.live = self.console.is_terminal if live is None else live
        self.k = 0
        self.mu_peak = math.nan
        self.next_omega: float | None = None
        self.replayed = 0
        self.measured = 0
        self.last_index = 0
        self._progress: Progress | None = None
        self._task = None
        self._dwell_task = None
        self._status_task = None
        self._dwell_started: float | None = None
        self._dwell_total: float | None = None
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None

    # -- context -------------------------------------------------------------------------
    def __enter__(self) -> "CampaignProgress":
        if self.live:
            # three short rows, so an 80-column terminal shows every word: the measurement count,
            # the current dwell, and the campaign status (iteration, mu-bar, next frequency)
            self._progress = _CampaignBars(
                SpinnerColumn(),
                TextColumn("{task.description}"),
                BarColumn(bar_width=16),
                MofNCompleteColumn(),
                TimeElapsedColumn(),
                TextColumn("{task.fields[status]}"),
                console=self.console,
                transient=False,
            )
            self._progress.start()
            self._task = self._progress.add_task("measurements", total=None, status="")
            self._dwell_task = self._progress.add_task("waiting", total=None, status="")
            self._status_task = None
            self._stop.clear()
            self._ticker = threading.Thread(target=self._tick, name="dwell-progress", daemon=True)
            self._ticker.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._ticker is not None:
            self._ticker.join(timeout=2.0)
            self._ticker = None
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def _tick(self) -> None:
        """Advance the dwell bar with the wall clock (the dwell itself reports nothing until done)."""
        while not self._stop.wait(0.2):
            started, total, progress = self._dwell_started, self._dwell_total, self._progress
            if started is None or progress is None or self._dwell_task is None:
                continue
            elapsed = time.monotonic() - started
            if total:
                progress.update(self._dwell_task, completed=min(elapsed, 0.99 * total))
            progress.update(self._dwell_task, status=f"{elapsed:.0f} s")

    # -- events --------------------------------------------------------------------------
    def _status(self) -> str:
        parts = []
        if self.k:
            parts.append(f"iteration {self.k}: mu-bar {format_mu(self.mu_peak)}")
        if self.next_omega is not None:
            parts.append(f"next {format_frequency(self.next_omega)}")
        return ", ".join(parts)

    def _show_status(self) -> None:
        if self._progress is not None:
            self._progress.status_text = self._status()
            self._progress.refresh()

    def _line(self, text: str) -> None:
        self.console.print(text, highlight=False, markup=False)

    def __call__(self, event: str, **info: Any) -> None:
        if event == "measure":
            self._measure(**info)
        elif event == "iteration":
            self._set_dwell(f"iteration {info.get('k')}: choosing the next frequency", None, running=False)
            self.k = int(info.get("k", self.k))
            self.mu_peak = float(info.get("mu_peak", math.nan))
            self.next_omega = None
            self._show_status()
            safeguard = info.get("safeguard")
            extra = f" [{safeguard}]" if safeguard and safeguard != "new-design" else ""
            if info.get("mu_peak_certified") is False and math.isfinite(self.mu_peak):
                extra += " (not certified between grid points: the goal cannot be claimed)"
            rig = info.get("rig_s")
            rig_text = f", rig time {format_duration(float(rig))}" if rig else ""
            design = info.get("design")
            design_text = f", {design} design" if design else ""
            self._line(
                f"iteration {self.k}: {info.get('n_points')} points, mu-bar peak {format_mu(self.mu_peak)}"
                f" at {format_frequency(float(info.get('mu_peak_omega', math.nan)))}{design_text}{rig_text}{extra}"
            )
            floor = tuple(info.get("floor_modes") or ())
            if floor:
                from setmem_hil.model.mu_floor import floor_sentence

                sentences = info.get("floor_sentences") or [floor_sentence(m) for m in floor]
                self._line(f"iteration {self.k}: {'; '.join(sentences)}")
            for line in output_lines(info.get("outputs")):
                self._line(line)
        elif event == "note" and info.get("kind") == "left-out":
            self._line(str(info.get("message", "")))
        elif event == "chosen":
            self.next_omega = float(info["next_omega"])
            self._show_status()
            self._line(f"iteration {info.get('k')}: next frequency {format_frequency(self.next_omega)}")
        elif event == "finished":
            summary = info.get("summary")
            self.next_omega = None  # nothing comes next: never show a stale choice
            if self._progress is not None and self._task is not None:
                self._progress.update(self._task, total=self.last_index, completed=self.last_index, description="done")
                self._show_status()
                self._set_dwell("finished", None, running=False)
                self._progress.update(self._dwell_task, visible=False)
            if summary is not None:
                reached = "goal reached" if getattr(summary, "reached_goal", False) else f"stopped ({getattr(summary, 'stop_reason', '?')})"
                rig = float(getattr(summary, "rig_s", 0.0) or 0.0)
                self._line(
                    f"finished: {reached}; mu-bar {format_mu(float(getattr(summary, 'final_mu_peak', math.nan)))} after "
                    f"{getattr(summary, 'experiments_added', '?')} added experiments"
                    + (f"; rig time {format_duration(rig)}" if rig else "")
                )
        if self.on_event is not None:
            self.on_event(event, **info)

    def _measure(self, index: int, total: int, omega_rad_s: float, replayed: bool = False, record_omegas: tuple = (),
                 **_: Any) -> None:
        if len(record_omegas) > 1:
            self._record(index, total, record_omegas)
            return
        self.last_index = int(index)
        if replayed:
            self.replayed += 1
        else:
            self.measured += 1
        if self._progress is not None and self._task is not None:
            if replayed:
                desc = f"replaying stored point {index}"
            else:
                planned = self._planned(omega_rad_s)
                desc = f"dwell {index} at {format_frequency(omega_rad_s)}" + (f", {planned:.3g} s" if planned else "")
            self._progress.update(self._task, total=total, completed=index - 1, description="measurements")
            if replayed:
                self._set_dwell(desc, None, running=False)
            else:
                self._set_dwell(desc, planned, running=True)
        elif not replayed:
            planned = self._planned(omega_rad_s)
            self._line(f"dwell {index}/{total} at {format_frequency(omega_rad_s)}" + (f" ({planned:.3g} s of excitation)" if planned else ""))
        elif index == 1:
            self._line("replaying the measurements stored in the journal")

    def _record(self, index: int, total: int, omegas: tuple) -> None:
        """A multisine record: one dwell measuring several points."""
        last = index + len(omegas) - 1
        self.last_index = last
        self.measured += len(omegas)
        desc = f"multisine record, points {index}-{last}/{total} at " + ", ".join(f"{w:.4g}" for w in omegas) + " rad/s"
        if self._progress is not None and self._task is not None:
            self._progress.update(self._task, total=total, completed=index - 1, description="measurements")
            self._set_dwell(desc, None, running=True)
        else:
            self._line(desc)

    def _set_dwell(self, description: str, total_s: float | None, running: bool) -> None:
        if self._progress is None or self._dwell_task is None:
            return
        self._dwell_started = time.monotonic() if running else None
        self._dwell_total = total_s if running else None
        self._progress.reset(self._dwell_task, total=total_s if running else None, description=description, status="")

    def _planned(self, omega_rad_s: float) -> float | None:
        if self.planned_dwell_s is None:
            return None
        try:
            return float(self.planned_dwell_s(omega_rad_s))
        except Exception:  # a display nicety must never stop a campaign
            return None


def output_lines(outputs: dict | None) -> list[str]:
    """Several sensors (issue 25): the shared natural-frequency intervals and each output's
    ``b0`` intervals, one line each (nothing for one sensor)."""
    if not outputs or len(outputs["names"]) < 2:
        return []
    lower, upper = outputs["lower"], outputs["upper"]

    def interval(lo, hi, fmt=".4g"):
        return f"[{lo:{fmt}}, {hi:{fmt}}]"

    poles = ", ".join(interval(math.sqrt(max(lo[1], 0.0)), math.sqrt(max(hi[1], 0.0))) for lo, hi in zip(lower[0], upper[0]))
    lines = [f"  shared natural frequencies (rad/s): {poles}"]
    for k, name in enumerate(outputs["names"]):
        residues = ", ".join(interval(lo[3], hi[3], ".3g") for lo, hi in zip(lower[k], upper[k]))
        lines.append(f"  {name}{' (control)' if k == 0 else ''}: b0 {residues}")
    return lines


def terminal_display(console: Console):
    """``display(experiment)`` for :mod:`setmem_hil.campaign.session`: a :class:`CampaignProgress`
    on ``console`` that shows each dwell's planned duration when the experiment can plan it."""
    from setmem_hil.model.experiment import PlanningExperiment

    def display(experiment) -> CampaignProgress:
        planned = None
        if isinstance(experiment, PlanningExperiment):
            def planned(omega_rad_s: float) -> float:
                plan = experiment.plan(omega_rad_s)
                return float(plan.skip_s + plan.window_s)
        return CampaignProgress(console, planned_dwell_s=planned)

    return display
