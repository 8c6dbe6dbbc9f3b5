"""Fuzzing the host side of the Modbus link: whatever the client returns, only typed errors escape."""

from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.exceptions import ConnectionException, ModbusIOException

from setmem_hil.drivers import modbus_registers as mr
from setmem_hil.drivers.transport import RetryPolicy
from setmem_hil.drivers.modbus_rig import ModbusLink
from setmem_hil.errors import DeviceError


class Reply:
    def __init__(self, registers=None, exception_code=None, function_code=3):
        self.registers = registers or []
        self.exception_code = exception_code
        self.function_code = function_code | (0x80 if exception_code is not None else 0)

    def isError(self):
        return self.exception_code is not None


class ScriptedClient:
    """Stands in for pymodbus's ModbusTcpClient: answers from a script, then raises timeouts."""

    connected = True

    def __init__(self, script):
        self.script = script

    def connect(self):
        return True

    def close(self):
        pass

    def _next(self):
        if not self.script:
            raise ModbusIOException("no response")
        item = self.script.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    def read_holding_registers(self, address, *, count, device_id):
        return self._next()

    def write_registers(self, address, values, *, device_id):
        return self._next()


replies = st.one_of(
    st.builds(Reply, st.lists(st.integers(0, 0xFFFF), max_size=130)),
    st.builds(Reply, st.none(), st.integers(0, 255)),
    st.sampled_from([ModbusIOException("timeout"), ConnectionException("reset")]),
)


def _link(script):
    link = ModbusLink.__new__(ModbusLink)
    link.host, link.port, link.framer, link.unit = "127.0.0.1", 0, "socket", 1
    link.retry = RetryPolicy(0.001, 3, 0.0, 0.0)
    link.where = "Modbus fuzz"
    from setmem_hil.drivers.transport import TransportStats

    link.stats = TransportStats()
    shared = list(script)
    link._open = lambda: setattr(link, "_client", ScriptedClient(shared))
    link._open()
    return link


@settings(max_examples=200, deadline=None)
@given(script=st.lists(replies, max_size=8))
def test_random_replies_give_a_value_or_a_typed_error(script):
    link = _link(script)
    for call in (
        lambda: link.read(0, mr.N_CONTROL_REGISTERS, "control", mr.decode_control_block),
        lambda: link.read(mr.page_address(0), mr.PAGE_REGISTERS, "page 0", lambda r: mr.decode_page(r, 1, 0)),
        lambda: link.write(mr.REG_ENABLE, [0], "enable"),
    ):
        try:
            call()
        except DeviceError:
            pass


def test_busy_then_good_reply_is_retried_and_a_bad_address_is_not():
    good = [0] * mr.N_CONTROL_REGISTERS
    good[mr.REG_MAGIC], good[mr.REG_VERSION] = mr.MAGIC, mr.VERSION
    link = _link([Reply(None, 6), Reply(good[:5]), Reply(good)])
    assert link.read(0, mr.N_CONTROL_REGISTERS, "control", mr.decode_control_block).status == 0
    assert link.stats.as_dict() == {"busy_exceptions": 1, "malformed_replies": 1, "reconnects": 1, "retries": 2}
    link = _link([Reply(None, 2), Reply(good)])
    try:
        link.read(0, mr.N_CONTROL_REGISTERS, "control", mr.decode_control_block)
    except mr.ModbusExceptionError as exc:
        assert exc.code == 2
    else:
        raise AssertionError("exception code 2 must not be retried")
