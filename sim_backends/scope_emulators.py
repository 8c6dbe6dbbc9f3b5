"""Emulated oscilloscopes on the emulated bench: Rigol DS1000Z and Keysight InfiniiVision X (issue 26).

Written from the programming guides (not from our driver):

* **Rigol DS1000Z** ("MSO1000Z/DS1000Z Series Programming Guide"): ``:CHANnel<n>:DISPlay``,
  ``:SCALe``, ``:OFFSet``, ``:COUPling``, ``:PROBe``; ``:TIMebase[:MAIN]:SCALe`` and ``:OFFSet``
  (the screen is 12 divisions, offset 0 puts the trigger at its centre); ``:ACQuire:MDEPth``
  (by channels on: 12k/120k/1.2M/12M/24M for one, half for two, a quarter for three or four);
  ``:TRIGger:EDGe:SOURce`` (``CHAN<n>``; no EXT input on the -Z models) and ``:LEVel``;
  ``:SINGle`` and ``:TRIGger:STATus?`` (``WAIT`` armed, ``STOP`` once the record is taken);
  ``:WAVeform:SOURce``, ``:MODE RAW``, ``:FORMat BYTE``, ``:STARt``/``:STOP`` (at most 250000
  points per ``:WAVeform:DATA?``, a ``#9`` block), ``:PREamble?``; BYTE codes: 25 codes a
  division, ``yreference`` 127, ``yorigin`` the offset in codes, the ADC's rails 0 and 255.
* **Keysight InfiniiVision X** (2000 X-Series Programmer's Guide): ``:CHANnel<n>:DISPlay``,
  ``:SCALe``, ``:OFFSet``; ``:TIMebase:SCALe`` (10 divisions) and ``:REFerence LEFT`` (the
  trigger one division from the left edge); ``:TRIGger:EDGE:SOURce`` (``CHANnel<n>`` or
  ``EXTernal``) and ``:LEVel``; ``:SINGle`` and ``:OPERegister:CONDition?`` (bit 3, Run, set
  until the single acquisition completes); ``:WAVeform:POINts`` (``:POINts:MODE``),
  ``:FORMat BYTE|WORD|ASCii``, ``:BYTeorder``, ``:UNSigned``, ``:PREamble?`` and ``:DATA?``
  (one ``#8`` block); in BYTE/WORD ``0`` is a hole, ``1`` clipped low, ``0xFF``/``0xFFFF``
  clipped high, WORD is the 8-bit sample left-shifted.

The channels are wired by the caller (``wiring``: channel -> ``"force"``, ``"response"``,
``"response2"``..., ``"sync"``, or ``"drive"``: the generator's output through a BNC tee, as
``setmem-hil calibrate-channels`` asks). Each input's gain is off by a fixed fraction, part the
channel's and part its V/div setting's (:meth:`ScopeEmulator.gain`). Each channel adds a white noise of ``noise_div`` divisions
RMS before the 8-bit ADC. The trigger is the generator's sync output's rising edge (a channel
wired to ``"sync"``, or EXT), or the force channel's rising zero crossing (the same instant);
nothing triggers while the generator's output is off.
"""

from __future__ import annotations

import math
import re

import numpy as np

from setmem_hil.drivers.instruments.scpi_commands import canonical_header
from setmem_hil.sim_backends.instrument_bench import EmulatedBench
from setmem_hil.sim_backends.instrument_emulators import UNDEFINED_HEADER, SettingsConflict, _Emulator, _number, _split

__all__ = ["ScopeEmulator", "RigolScopeEmulator", "KeysightScopeEmulator"]

SYNC_HIGH_V = 3.3  # the generator's sync output: a logic level


class ScopeEmulator(_Emulator):
    """What both scopes share: channels, arming, the triggered record, the ADC."""

    n_channels = 4
    time_divisions = 10.0
    adc_span_div = 10.24  # the 8-bit ADC's span in divisions
    max_rate_hz = 1e9

    def __init__(self, bench: EmulatedBench, wiring: dict[int, str], volt_per_unit: dict[str, float], noise_div: float = 0.02,
                 seed: int = 7, gain_error: float = 0.015):
        super().__init__(bench)
        self.wiring, self.volt_per_unit, self.noise_div = dict(wiring), dict(volt_per_unit), float(noise_div)
        self.channel = {c: {"DISP": c == 1, "SCAL": 1.0, "OFFS": 0.0, "COUP": "DC", "PROB": 1.0, "VERN": False} for c in range(1, self.n_channels + 1)}
        self.time_scale = 1e-3
        self.time_offset = 0.0
        self.trigger_source = "CHAN1"
        self.trigger_level = 0.0
        self.armed = False
        self.ready_at = math.inf  # clock time the armed record completes
        self.codes: dict[int, np.ndarray] = {}
        self.record_t0 = 0.0
        self.record_dt = 1e-6
        self.wave_source = 1
        self.running = True
        self.rng = np.random.default_rng(seed)
        # each input's vertical gain is off by a fixed fraction (within the datasheets' figures):
        # two thirds of it the channel's own, a third the scale's (each V/div setting switches
        # its own attenuator and amplifier gain); ``seed`` is this unit's: its serial number
        self.channel_errors = {c: float(e) for c, e in zip(self.channel, self.rng.uniform(-gain_error, gain_error, self.n_channels) * 2 / 3)}
        self.scale_error_span = gain_error / 3
        self.unit_seed = int(seed)
        self.idn = self.idn.replace(self.serial, f"{self.serial[:-5]}{self.unit_seed % 100000:05d}")
        self.short_by = 0  # tests: the next data transfer loses this many points
        self.bad_header = False  # tests: the next data transfer has a malformed block header

    # -- the record ------------------------------------------------------------------------------
    def handle(self, command: str) -> str | bytes | None:
        """What both guides share (common commands, channels, run/stop/single), then the model's own."""
        head, args = _split(command)
        query = head.endswith("?")
        nodes = canonical_header(head.rstrip("?"))
        if nodes and nodes[0].startswith("*") or nodes == ("SYST", "ERR"):
            return self._common(nodes, query)
        m = re.fullmatch(r"CHAN(\d)", nodes[0]) if nodes else None
        if m and len(nodes) == 2 and 1 <= int(m.group(1)) <= self.n_channels:
            return self._channel_command(int(m.group(1)), nodes[1], args, query)
        if nodes in (("STOP",), ("RUN",)):
            self.running = nodes == ("RUN",)
            return None
        if nodes == ("SING",):
            self.running = False  # a single acquisition: armed, then stopped once it has triggered
            self.arm()
            return None
        if nodes and nodes[0] == "WAV":
            return self._waveform(nodes[1:], args, query)
        if nodes in (("TFOR",), ("TRIG", "FORC")):  # Rigol :TFORce, Keysight :TRIGger:FORCe
            if self.armed and self.ready_at == math.inf:
                self._take(self.bench.clock.now() + self.pretrigger_s())
            return None
        return self._model_command(nodes, args, query)

    def _model_command(self, nodes: tuple[str, ...], args: str, query: bool) -> str | bytes | None:  # pragma: no cover - per model
        raise NotImplementedError

    def _waveform(self, nodes: tuple[str, ...], args: str, query: bool) -> str | bytes | None:
        """``:WAVeform`` (both guides): the source, the preamble and the data; the model's own settings."""
        if nodes == ("SOUR",):
            return self._waveform_source(args, query)
        if nodes == ("PRE",) and query:
            return self._preamble()
        if nodes == ("DATA",) and query:
            return self._data()
        return self._waveform_setting(nodes, args, query)

    def _waveform_setting(self, nodes: tuple[str, ...], args: str, query: bool) -> str | None:  # pragma: no cover - per model
        raise NotImplementedError

    def _preamble(self) -> str:  # pragma: no cover - per model
        raise NotImplementedError

    def _data(self) -> bytes:  # pragma: no cover - per model
        raise NotImplementedError

    def channels_on(self) -> list[int]:
        return [c for c, s in self.channel.items() if s["DISP"]]

    def record_points(self) -> int:  # pragma: no cover - per model
        raise NotImplementedError

    def pretrigger_s(self) -> float:  # pragma: no cover - per model
        raise NotImplementedError

    def arm(self) -> None:
        """Find the trigger instant and take the record from the bench at once (the bench
        cannot go back in time); it becomes readable when the clock passes its end. Armed again
        before an earlier record's end (a driver that gave up waiting for a reply and retries),
        the scope first finishes that acquisition: the clock is advanced to its end (virtual
        time; a scope busy acquiring answers its next command late). In the normal order, the
        record read before the next arm, nothing changes."""
        behind = self.bench.t - self.bench.clock.now()
        if behind > 0:
            self.bench.clock.sleep(behind)
        now = self.bench.clock.now()
        self.armed = True
        self.ready_at = math.inf
        if not self._trigger_can_fire():
            return
        if self._trigger_source_signal() == "force":
            edge = self.bench.force_rising_after(now + self.pretrigger_s(),
                                                 self.trigger_level / (self.volt_per_unit["force"] * self.gain(self._trigger_channel())))
        elif self._trigger_source_signal() == "drive":  # a tee'd generator output (channel match)
            edge = self.bench.force_rising_after(now + self.pretrigger_s(),
                                                 self.trigger_level / self.gain(self._trigger_channel()) * self.bench.true_gain)
        else:
            edge = self.bench.sync_edge_after(now + self.pretrigger_s())
        if edge is None:
            return
        self._take(edge)

    def _take(self, edge: float) -> None:
        """The record around trigger instant ``edge``, from the bench, at once."""
        n = self.record_points()
        length = self.time_divisions * self.time_scale
        dt = length / n
        t0 = edge - self.pretrigger_s()
        force, outputs = self.bench.record(t0, dt, n)
        self.record_t0, self.record_dt = t0 - edge, dt
        signals = {"force": force, "drive": force / self.bench.true_gain, "sync": np.where(np.sin(2 * math.pi * self.bench.frequency_hz * (np.arange(n) * dt - (edge - t0))) >= 0,
                                                    SYNC_HIGH_V, 0.0)}
        for k, name in enumerate(self.bench.response_names(outputs.shape[0])):
            signals[name] = outputs[k]
        self.codes = {c: self._adc(c, self._volts(c, signals)) for c in self.channels_on()}
        self.ready_at = t0 + length

    def _trigger_source_command(self, args: str, query: bool, allowed: str) -> str | None:
        """The edge trigger's source (both guides): one of ``allowed`` (a regular expression)."""
        if query:
            return self.trigger_source
        source = canonical_header(args)[0] if args else ""
        if not re.fullmatch(allowed, source):
            raise ValueError(args)
        self.trigger_source = source
        return None

    def _trigger_level_command(self, args: str, query: bool, answer: str) -> str | None:
        """The edge trigger's level in volts (both guides; ``answer`` the model's number format)."""
        if query:
            return answer.format(self.trigger_level)
        self.trigger_level = _number(args)
        return None

    def _trigger_channel(self) -> int | None:
        m = re.fullmatch(r"CHAN(\d)", self.trigger_source)
        return int(m.group(1)) if m else None

    def _trigger_source_signal(self) -> str | None:
        """What the trigger source is wired to: "sync", "force", a response, or None."""
        if self.trigger_source == "EXT":
            return "sync" if self.has_ext_sync else None
        ch = self._trigger_channel()
        return self.wiring.get(ch) if ch is not None else None

    def _trigger_can_fire(self) -> bool:
        source = self._trigger_source_signal()
        if source == "sync":
            return 0.0 < self.trigger_level < SYNC_HIGH_V
        if source == "force":  # a zero crossing of the force: a level inside its swing
            return abs(self.trigger_level) < self.bench.force_amplitude_n * self.volt_per_unit.get("force", 1.0)
        if source == "drive":
            return abs(self.trigger_level) < self.bench.force_amplitude_n / self.bench.true_gain
        return False

    has_ext_sync = False  # the generator's sync wired to EXT (Keysight)

    def _volts(self, channel: int, signals: dict[str, np.ndarray]) -> np.ndarray:
        name = self.wiring.get(channel)
        n = next(iter(signals.values())).size
        per_unit = 1.0 if name in ("sync", "drive") else self.volt_per_unit.get(name, 1.0)
        clean = np.zeros(n) if name is None else signals[name] * (1.0 if name == "sync" else per_unit * self.gain(channel))
        return clean + self.noise_div * self.channel[channel]["SCAL"] * self.rng.standard_normal(n)

    def gain(self, channel: int) -> float:
        """The channel's true gain at its present scale (the emulation's truth; tests read it)."""
        scale = self.channel[channel]["SCAL"]
        key = int(round(math.log10(scale) * 1e4)) + 100000
        own = np.random.default_rng((self.unit_seed, channel, key)).uniform(-1.0, 1.0) * self.scale_error_span
        return 1.0 + self.channel_errors[channel] + float(own)

    def _adc(self, channel: int, volts: np.ndarray) -> np.ndarray:
        """8-bit codes 0..255, 127 at the offset, the span ``adc_span_div`` divisions."""
        s = self.channel[channel]
        per_code = s["SCAL"] * self.adc_span_div / 256.0
        return np.clip(np.round((volts + s["OFFS"]) / per_code) + 127, 0, 255).astype(np.int64)

    def done(self) -> bool:
        return self.armed and self.bench.clock.now() >= self.ready_at

    def _record_codes(self) -> np.ndarray:
        """The selected channel's codes of the completed record (none before it is complete)."""
        if not self.done() or self.wave_source not in self.codes:
            return np.zeros(0, dtype=np.int64)
        return self.codes[self.wave_source]

    def _waveform_source(self, args: str, query: bool) -> str | None:
        """``:WAVeform:SOURce CHANnel<n>`` (both guides)."""
        if query:
            return f"CHAN{self.wave_source}"
        m = re.fullmatch(r"CHAN(\d)", canonical_header(args)[0] if args else "")
        if not m:
            raise ValueError(args)
        self.wave_source = int(m.group(1))
        return None

    # -- common commands -------------------------------------------------------------------------
    def _common(self, nodes: tuple[str, ...], query: bool) -> str | None:
        if nodes == ("*IDN",) and query:
            return self.idn
        if nodes == ("SYST", "ERR") and query:
            return self.errors.pop(0) if self.errors else self.no_error
        if nodes in (("*CLS",), ("*RST",)):
            self.errors.clear()
            return None
        if nodes == ("*OPC",):
            return "1" if query else None
        return self._undefined(query)

    def _undefined(self, query: bool) -> None:
        self.errors.append(UNDEFINED_HEADER)
        return None

    def _channel_command(self, ch: int, node: str, args: str, query: bool) -> str | None:
        keys = {"DISP": "DISP", "SCAL": "SCAL", "OFFS": "OFFS", "COUP": "COUP", "PROB": "PROB", **({"VERN": "VERN"} if self.has_vernier else {})}
        if node not in keys:
            return self._undefined(query)
        state = self.channel[ch]
        if query:
            v = state[node]
            return ("1" if v else "0") if node in ("DISP", "VERN") else (v if isinstance(v, str) else f"{v:.6e}")
        if node in ("DISP", "VERN"):
            state[node] = args.upper() in ("1", "ON")
        elif node == "COUP":
            state["COUP"] = args.upper()
        else:
            v = _number(args)
            if node == "SCAL" and not self.scale_min <= v <= self.scale_max:
                raise ValueError(args)
            if node == "SCAL" and self.has_vernier and not state["VERN"]:
                v = _coarse_step(v)  # coarse adjustment: the 1-2-5 step at or above (DS1000Z guide, :CHANnel<n>:SCALe)
            state[node] = v
        return None

    scale_min, scale_max = 1e-3, 10.0
    has_vernier = False  # :CHANnel<n>:VERNier (Rigol): fine scales only when on; the others take any scale

    def _block(self, payload: bytes, digits: int) -> bytes:
        if self.bad_header:
            self.bad_header = False
            return b"#X" + payload
        return f"#{digits}{len(payload):0{digits}d}".encode("ascii") + payload


def _coarse_step(v: float) -> float:
    decade = 10.0 ** math.floor(math.log10(v) + 1e-9)
    return next(m * decade for m in (1.0, 2.0, 5.0, 10.0) if m * decade >= v * (1 - 1e-9))


class RigolScopeEmulator(ScopeEmulator):
    """A Rigol DS1104Z (module docstring)."""

    has_vernier = True

    idn = "RIGOL TECHNOLOGIES,DS1104Z,DS1ZA123456789,00.04.04.SP4"
    serial = "DS1ZA123456789"
    no_error = '0,"No error"'
    time_divisions = 12.0
    adc_span_div = 256 / 25.0  # 25 codes a division
    depths = {1: (12000, 120000, 1200000, 12000000, 24000000), 2: (6000, 60000, 600000, 6000000, 12000000),
              3: (3000, 30000, 300000, 3000000, 6000000), 4: (3000, 30000, 300000, 3000000, 6000000)}
    MAX_BYTES = 250000

    def __init__(self, bench, wiring, volt_per_unit, noise_div: float = 0.02, **options):
        super().__init__(bench, wiring, volt_per_unit, noise_div, **options)
        self.mdep = 12000
        self.wave = {"MODE": "NORM", "FORM": "BYTE", "STAR": 1, "STOP": 1200}

    def record_points(self) -> int:
        return self.mdep

    def pretrigger_s(self) -> float:
        return max(0.0, self.time_divisions / 2 * self.time_scale - self.time_offset)

    def _model_command(self, nodes: tuple[str, ...], args: str, query: bool) -> str | bytes | None:
        if nodes in (("TIM", "MAIN", "SCAL"), ("TIM", "SCAL")):
            if query:
                return f"{self.time_scale:.6e}"
            self.time_scale = _number(args)
            return None
        if nodes in (("TIM", "MAIN", "OFFS"), ("TIM", "OFFS")):
            if query:
                return f"{self.time_offset:.6e}"
            self.time_offset = _number(args)
            return None
        if nodes == ("ACQ", "MDEP"):
            if query:
                return str(self.mdep)
            if not self.running:  # users' reports: refused in STOP (and single) with -221
                raise SettingsConflict(args)
            n_on = max(1, len(self.channels_on()))
            value = int(_number(args))
            if value not in self.depths[n_on]:  # the guide: only the depths of the channels on
                raise ValueError(args)
            self.mdep = value
            return None
        if nodes == ("ACQ", "SRAT") and query:
            return f"{self.mdep / (self.time_divisions * self.time_scale):.6e}"
        if nodes in (("ACQ", "TYPE"), ("TRIG", "MODE"), ("TRIG", "EDG", "SLOP"), ("TRIG", "SWE")):
            return None if not query else "NORM"
        if nodes == ("TRIG", "EDG", "SOUR"):
            return self._trigger_source_command(args, query, r"CHAN[1-4]|AC")  # the -Z models have no EXT input
        if nodes == ("TRIG", "EDG", "LEV"):
            return self._trigger_level_command(args, query, "{:.6e}")
        if nodes == ("TRIG", "STAT") and query:
            return "STOP" if self.done() else ("WAIT" if self.armed else "STOP")
        return self._undefined(query)

    def _waveform_setting(self, nodes, args: str, query: bool):
        if nodes in (("MODE",), ("FORM",)):
            if query:
                return self.wave[nodes[0]]
            self.wave[nodes[0]] = canonical_header(args)[0]
            return None
        if nodes in (("STAR",), ("STOP",)):
            if query:
                return str(self.wave[nodes[0]])
            self.wave[nodes[0]] = int(_number(args))
            return None
        return self._undefined(query)

    def _preamble(self) -> str:
        s = self.channel[self.wave_source]
        points = self._record_codes().size
        yinc = s["SCAL"] / 25.0
        yorigin = round(s["OFFS"] / yinc)
        return (f"0,0,{points},1,{self.record_dt:.6e},{self.record_t0:.6e},0,{yinc:.6e},{yorigin},127")

    def _data(self) -> bytes:
        codes = self._record_codes()
        lo, hi = self.wave["STAR"], min(self.wave["STOP"], codes.size)
        if hi - lo + 1 > self.MAX_BYTES:
            raise ValueError("more than 250000 points in one transfer")
        payload = codes[lo - 1:hi].astype(np.uint8).tobytes()
        if self.short_by:
            payload, self.short_by = payload[:-self.short_by], 0
        return self._block(payload, 9)


class KeysightScopeEmulator(ScopeEmulator):
    """A Keysight DSOX2024A (module docstring); ``ext_sync``: the generator's sync on EXT."""

    idn = "KEYSIGHT TECHNOLOGIES,DSO-X 2024A,MY58123456,02.65.2021030741"
    serial = "MY58123456"
    no_error = '+0,"No error"'
    time_divisions = 10.0
    adc_span_div = 10.0
    scale_max = 5.0

    def __init__(self, bench, wiring, volt_per_unit, noise_div: float = 0.02, ext_sync: bool = True, **options):
        super().__init__(bench, wiring, volt_per_unit, noise_div, **options)
        self.has_ext_sync = ext_sync
        self.reference = "CENT"
        self.wave = {"POIN": 1000, "MODE": "NORM", "FORM": "BYTE", "BYT": "MSBF", "UNS": True}

    def record_points(self) -> int:
        return int(self.wave["POIN"])

    def pretrigger_s(self) -> float:
        return {"LEFT": 1.0, "CENT": 5.0, "RIGH": 9.0}[self.reference] * self.time_scale

    def _model_command(self, nodes: tuple[str, ...], args: str, query: bool) -> str | bytes | None:
        if nodes == ("TIM", "SCAL"):
            if query:
                return f"{self.time_scale:+.6E}"
            self.time_scale = _number(args)
            return None
        if nodes == ("TIM", "REF"):
            if query:
                return self.reference
            self.reference = canonical_header(args)[0][:4]
            return None
        if nodes in (("ACQ", "TYPE"), ("TRIG", "MODE"), ("TRIG", "EDGE", "SLOP"), ("TRIG", "SWE")):
            return None if not query else "NORM"
        if nodes == ("TRIG", "EDGE", "SOUR"):
            return self._trigger_source_command(args, query, r"CHAN[1-4]|EXT")
        if nodes == ("TRIG", "EDGE", "LEV"):
            return self._trigger_level_command(args, query, "{:+.6E}")
        if nodes == ("OPER", "COND") and query:
            return "+0" if self.done() or not self.armed else "+8"
        return self._undefined(query)

    def _waveform_setting(self, nodes, args: str, query: bool):
        if nodes == ("POIN",):
            if query:
                return str(self._record_codes().size or self.wave["POIN"])
            self.wave["POIN"] = int(_number(args))
            return None
        if nodes in (("POIN", "MODE"), ("FORM",), ("BYT",)):
            key = nodes[-1] if nodes[-1] != "MODE" else "MODE"
            if query:
                return self.wave[key]
            self.wave[key] = canonical_header(args)[0]
            return None
        if nodes == ("UNS",):
            if query:
                return "1" if self.wave["UNS"] else "0"
            self.wave["UNS"] = args.upper() in ("1", "ON")
            return None
        return self._undefined(query)

    def _scaling(self) -> tuple[float, float, float]:
        """yincrement, yorigin (volts), yreference in the current format's codes."""
        s = self.channel[self.wave_source]
        per_adc_code = s["SCAL"] * self.adc_span_div / 256.0
        if self.wave["FORM"] == "WORD":
            return per_adc_code / 256.0, -s["OFFS"], 32768.0
        return per_adc_code, -s["OFFS"], 128.0

    def _preamble(self) -> str:
        fmt = {"BYTE": 0, "WORD": 1, "ASC": 4}[self.wave["FORM"]]
        yinc, yorigin, yref = self._scaling()
        return (f"+{fmt},+0,+{self._record_codes().size},+1,{self.record_dt:+.6E},{self.record_t0:+.6E},+0,"
                f"{yinc:+.6E},{yorigin:+.6E},+{int(yref)}")

    def _data(self) -> bytes:
        adc = self._record_codes()
        # the emulated ADC's codes are centred on 127; this scope's on 128: shift by one, and
        # mark the rails as the guide says (1 clipped low, 0xFF / 0xFFFF clipped high)
        low, high = adc <= 0, adc >= 255
        shifted = np.clip(adc + 1, 2, 254)
        fmt = self.wave["FORM"]
        if fmt == "ASC":
            yinc, yorigin, yref = self._scaling()
            text = ",".join(f"{(c - yref) * yinc + yorigin:+.6E}" for c in shifted)
            payload = text.encode("ascii")
            return self._block(payload, 8)
        if fmt == "WORD":
            words = np.where(low, 1, np.where(high, 0xFFFF, shifted << 8)).astype(">u2" if self.wave["BYT"] == "MSBF" else "<u2")
            payload = words.tobytes()
        else:
            payload = np.where(low, 1, np.where(high, 0xFF, shifted)).astype(np.uint8).tobytes()
        if self.short_by:
            payload, self.short_by = payload[:-self.short_by * (2 if fmt == "WORD" else 1)], 0
        return self._block(payload, 8)
