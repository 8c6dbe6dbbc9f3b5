"""What every SCPI-profile instrument shares: identity check, init sequence, error queue, read-back."""

from __future__ import annotations

import logging
import math
import re
from typing import Callable, TypeVar

from setmem_hil.drivers.instruments.profile import LockInProfile, ScpiGeneratorProfile, Setting
from setmem_hil.drivers.instruments.scpi_commands import fill_fields, parse_number, pick_reply, render
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceIdentityError, DeviceRejectedError

__all__ = ["ScpiInstrument"]

log = logging.getLogger(__name__)

MAX_ERROR_READS = 20
T = TypeVar("T")


class ScpiInstrument:
    """One instrument behind a :class:`VisaLink`, interpreted through its profile."""

    def __init__(self, name: str, profile: ScpiGeneratorProfile | LockInProfile, link: VisaLink, fields: dict | None = None):
        self.name, self.profile, self.link = name, profile, link
        self.model = profile.model
        self.fields = dict(fields or {})
        self.garbled_replies = 0  # answers that did not parse the first time (logged as warnings; tests read it)

    @property
    def where(self) -> str:
        return f"{self.name} ({self.link.resource})"

    def reconnect(self) -> None:
        """A fresh connection to the same resource (after the link failed)."""
        self.link.reopen()

    def query_parsed(self, command: str, parse: Callable[[str], T], what: str) -> T:
        """Query and parse; an answer that does not parse (garbled on the line) is asked for once
        more before it is an error (exit 4) naming the instrument, the query and the answer."""
        reply = self.link.query(command)
        try:
            return parse(reply)
        except ValueError as first:
            log.warning("%s: %r answered %r (%s); asking again", self.where, command, reply, first)
            self.garbled_replies += 1
        reply = self.link.query(command)
        try:
            return parse(reply)
        except ValueError as exc:
            raise DeviceRejectedError("garbled", f"{self.where}: {what}: {command!r} answered {reply!r} twice in a form that "
                                                 f"does not parse ({exc})") from None

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
            if rule.startswith("mask:"):
                status = self.query_parsed(self.profile.error_query, lambda r: int(parse_number(r)), "error status")
                if status & int(rule[5:]):
                    found.append(f"{self.profile.error_query} = {status}")
                break  # a status register: one read clears it
            reply = self.link.query(self.profile.error_query)
            if re.search(rule, reply):
                break
            found.append(reply)
        if found:
            raise DeviceRejectedError("instrument", f"{self.where}: the instrument reported {'; '.join(found)} after {after!r}")

    def run_init(self) -> None:
        """The profile's init sequence, the error queue read after each command (so an error
        names the command that caused it)."""
        for template in self.profile.init:
            self.send(template)
            self.check_errors(render(template, **self.fields))

    def set_checked(self, setting: Setting, value: float | None = None, label: str = "") -> None:
        """Send a setting, read it back (number within tolerance, or the expected text), check errors."""
        fields = {} if value is None else {"value": value}
        command = render(setting.set, **self.fields, **fields)
        self.link.write(command)
        if setting.query:
            query = render(setting.query, **self.fields)
            if setting.expect:
                expect = fill_fields(setting.expect, **self.fields)
                got_text = self.query_parsed(query, self._picker(setting, str), f"read-back of {command!r}")
                if got_text.upper() != expect.strip().upper():
                    raise DeviceRejectedError("instrument", f"{self.where}: after {command!r} the instrument reads back {got_text!r}, expected {expect!r}")
            elif value is not None:
                got = self.query_parsed(query, self._picker(setting, parse_number), f"read-back of {command!r}")
                if not math.isclose(got, value, rel_tol=max(setting.tolerance_rel, 1e-12), abs_tol=setting.resolution):
                    raise DeviceRejectedError("instrument", f"{self.where}: {label or 'value'} set to {value:.10g}, the instrument reads back "
                                                            f"{got:.10g} (after {command!r}; tolerance_rel {setting.tolerance_rel:g}, resolution {setting.resolution:g})")
        self.check_errors(command)

    def _picker(self, setting: Setting, convert: Callable[[str], T]) -> Callable[[str], T]:
        """Answer -> value through the setting's ``reply`` pattern (ValueError when absent)."""
        pattern = fill_fields(setting.reply, **self.fields)

        def pick(reply: str) -> T:
            text = pick_reply(reply, pattern)
            if text is None:
                raise ValueError(f"no match for reply pattern {pattern!r}")
            return convert(text)

        return pick

    def close(self) -> None:
        self.link.close()
