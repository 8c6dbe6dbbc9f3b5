"""The identity of a CANopen node: object 0x1018 read by SDO (``canopen``), before any output.

Sub-index 1 is the vendor id, 2 the product code (CiA 301). The check opens its own connection
to the bus (python-can allows several on one interface), so it works beside any other driver.
"""

from __future__ import annotations

from setmem_hil.drivers.instruments.profile import CanopenIdentity
from setmem_hil.errors import DeviceIdentityError, DeviceTimeoutError

__all__ = ["check_canopen_identity", "IDENTITY_OBJECT"]

IDENTITY_OBJECT = 0x1018


def check_canopen_identity(bus_args: dict, expected: CanopenIdentity, where: str, timeout_s: float = 0.5) -> str:
    """Read 0x1018 sub 1 and 2 of ``expected.node``; DeviceIdentityError naming what it answered."""
    import canopen

    network = canopen.Network()
    network.connect(**bus_args)
    try:
        node = canopen.RemoteNode(expected.node, canopen.ObjectDictionary())
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = timeout_s
        try:
            vendor = int.from_bytes(node.sdo.upload(IDENTITY_OBJECT, 1)[:4], "little")
            product = int.from_bytes(node.sdo.upload(IDENTITY_OBJECT, 2)[:4], "little")
        except canopen.SdoAbortedError as exc:
            raise DeviceIdentityError(f"{where}: CANopen node {expected.node} refused its identity object 0x1018 ({exc})") from None
        except canopen.SdoCommunicationError as exc:
            raise DeviceTimeoutError(f"{where}: CANopen node {expected.node} does not answer SDO requests ({exc})") from None
    finally:
        network.disconnect()
    if (vendor, product) != (expected.vendor_id, expected.product_code):
        raise DeviceIdentityError(f"{where}: CANopen node {expected.node} identity: expected vendor 0x{expected.vendor_id:08X} "
                                  f"product 0x{expected.product_code:08X}, it answered vendor 0x{vendor:08X} product 0x{product:08X}; "
                                  "nothing was switched on")
    return f"CANopen node {expected.node}: vendor 0x{vendor:08X} product 0x{product:08X}"
