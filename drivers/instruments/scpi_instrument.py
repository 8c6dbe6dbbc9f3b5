"""What every SCPI-profile instrument shares: identity check, init sequence, error queue, read-back."""

from __future__ import annotations

import math
import re

from setmem_hil.drivers.instruments.profile import LockInProfile, ScpiGeneratorProfile, Setting
from setmem_hil.drivers.instruments.scpi_commands import parse_number, render
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceIdentityError, DeviceRejectedError

__all__ = ["ScpiInstrument"]

MAX_ERROR_READS = 20


class ScpiInstrument:
    """One instrument behind a :class:`VisaLink`, interpreted through its profile."""

    def __init__(self, name: str, profile: ScpiGeneratorProfile | LockInProfile, link: VisaLink, fields: dict | None = None):
        self.name, self.profile, self.link = name, profile, link
        self.model = profile.model
        self.fields = dict(fields or {})

    @property
    def where(self) -> str:
        return f"{self.name} ({self.link.resource})"

    def check_identity(self) -> str:
        reply = self.link.query(self.profile.identity_query)
        if not re.search(self.profile.identity_expect, reply):
            raise DeviceIdentityError(f"{self.where}: expected a {self.model} (identity /{self.profile.identity_expect}/), "
                                      f"it answered {reply!r}; nothing was switched on")
        return reply

    def send(self, template: str, **values) -> None:
        self.link.write(render(template, **self.fields, **values))

    def ask(self, template: str, **values) -> str:
        return self.link.query(render(template, **self.fields, **values))

    def check_errors(self, after: str) -> None:
        """Read the error queue empty; raise naming every error and the command that caused it."""
        found = []
        rule = self.profile.no_error
        for _ in range(MAX_ERROR_READS):
            reply = self.link.query(self.profile.error_query)
            if rule.startswith("mask:"):
                try:
                    bad = int(parse_number(reply)) & int(rule[5:])
                except ValueError:
                    bad = 1
                if not bad:
                    break
                found.append(f"{self.profile.error_query} = {reply}")
                break  # a status register: one read clears it
            if re.search(rule, reply):
                break
            found.append(reply)
        if found:
            raise DeviceRejectedError("instrument", f"{self.where}: the instrument reported {'; '.join(found)} after {after!r}")

    def run_init(self) -> None:
        for template in self.profile.init:
            self.send(template)
        self.check_errors("the init sequence")

    def set_checked(self, setting: Setting, value: float | None = None, label: str = "") -> None:
        """Send a setting, read it back (number within tolerance, or the expected text), check errors."""
        fields = {} if value is None else {"value": value}
        command = render(setting.set, **self.fields, **fields)
        self.link.write(command)
        if setting.query:
            reply = self.ask(setting.query)
            if setting.expect:
                if reply.strip().upper() != setting.expect.upper():
                    raise DeviceRejectedError("instrument", f"{self.where}: after {command!r} the instrument reads back {reply!r}, expected {setting.expect!r}")
            elif value is not None:
                got = parse_number(reply)
                if not math.isclose(got, value, rel_tol=max(setting.tolerance_rel, 1e-12), abs_tol=0.0):
                    raise DeviceRejectedError("instrument", f"{self.where}: {label or 'value'} set to {value:.10g}, the instrument reads back {reply!r}")
        self.check_errors(command)

    def close(self) -> None:
        self.link.close()
