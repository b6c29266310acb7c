"""Modbus requests -> simulated drives -> replies (shared by the RTU line and TCP server)."""

from __future__ import annotations

from typing import Mapping

from ..transports import modbus_library  # noqa: F401 - the pymodbus version check, before pymodbus

# isort: split

from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterResponse,
)

from .model import SimException, SimulatedDrive


def execute(drive: SimulatedDrive, request: ModbusPDU) -> ModbusPDU:
    """One request on one drive: the reply PDU, or the drive's exception."""
    function = request.function_code
    try:
        drive.check_function(function)
        if function == 3:
            return ReadHoldingRegistersResponse(registers=drive.read(request.address,
                                                                     request.count))
        if function == 6:
            drive.write(request.address, [request.registers[0]])
            return WriteSingleRegisterResponse(address=request.address,
                                               registers=[request.registers[0]])
        if function == 16:
            drive.write(request.address, list(request.registers))
            return WriteMultipleRegistersResponse(address=request.address,
                                                  count=len(request.registers))
        if function == 8 and request.sub_function_code == 0:
            # Diagnostics, return query data: the echo the Modbus spec defines.
            return DecodePDU.pdu_sub_table[8][0][1](message=request.message)
        raise drive.exception('illegal_function')
    except SimException as exc:
        return ExceptionResponse(function, exc.code)


def answer(drives: Mapping[int, SimulatedDrive], request: ModbusPDU) -> ModbusPDU | None:
    """Return the reply on the line, or None (absent or silent drive, broadcast)."""
    unit = request.dev_id
    targets = list(drives.values()) if unit == 0 else [drives[unit]] if unit in drives else []
    reply = None
    for drive in targets:
        if drive.silent:
            continue
        drive.note_request()
        reply = execute(drive, request)
    if unit == 0 or reply is None or targets[0].mute:   # broadcasts are never answered
        return None
    reply.dev_id = unit
    reply.transaction_id = request.transaction_id
    return reply
