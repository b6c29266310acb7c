"""Commands preempt polls: a new velocity command goes on the wire before the next read."""

from __future__ import annotations

import math

from unit_support import MemoryTransport, shipped_profile
from vfd_ros2.control.controller import ControllerConfig, DriveController
from vfd_ros2.control.loop import CycleLoop
from vfd_ros2.drives.modbus import ModbusDrive
from vfd_ros2.protocol.scaling import VelocityScaling

SETPOINT = 0xE721    # BONENG AM P07.33


class CommandDuringPoll(MemoryTransport):
    """Delivers a velocity command while the poll's first status read is on the wire."""

    def __init__(self) -> None:
        super().__init__()
        self.on_first_read = None

    def read_registers(self, unit: int, address: int, count: int) -> list[int]:
        words = super().read_registers(unit, address, count)
        if self.on_first_read is not None:
            callback, self.on_first_read = self.on_first_read, None
            callback()
        return words


def controller_on(transport: MemoryTransport) -> DriveController:
    profile = shipped_profile('boneng_am')
    transport.registers[0xE101] = 1                 # P01.01 ready
    drive = ModbusDrive(profile, transport, 1, VelocityScaling(gear_ratio=10.0,
                                                               rated_speed_rpm=1330.0))
    return DriveController(drive, ControllerConfig(auto_enable=True,
                                                   apply_commissioning=False))


def test_a_command_arriving_mid_poll_is_written_before_the_remaining_reads():
    transport = CommandDuringPoll()
    controller = controller_on(transport)
    controller.step()                                # connect (forgets older commands)
    controller.command_velocity(1.0)
    controller.step()                                # write 1.0 and run, poll
    assert len(controller.drive.blocks) > 2
    transport.requests.clear()
    transport.on_first_read = lambda: controller.command_velocity(2.0)
    controller.poll_phase()
    kinds = [(kind, address) for kind, _unit, address, _data in transport.requests]
    first_read = kinds.index(next(k for k in kinds if k[0] == 'read'))
    # Right after the read during which it arrived: the new setpoint, then the other reads.
    assert kinds[first_read + 1] == ('write', SETPOINT)
    assert all(kind == 'read' for kind, _ in kinds[first_read + 2:])
    raw = transport.writes_to(SETPOINT)[-1]
    # 2 rad/s at the wheel x 10 = 191 rpm at the motor = 14.4 % of 1330 rpm, in 0.1 %.
    assert raw == round(2.0 * 10 * 60 / (2 * math.pi) / 1330 * 100 / 0.1) == 144


def test_a_repeated_command_waits_for_the_cycle():
    transport = CommandDuringPoll()
    controller = controller_on(transport)
    controller.step()
    controller.command_velocity(1.0)
    controller.step()
    transport.requests.clear()
    transport.on_first_read = lambda: controller.command_velocity(1.0)   # same value again
    controller.poll_phase()
    kinds = [kind for kind, *_ in transport.requests]
    assert kinds and set(kinds) == {'read'}


def test_the_loop_preempts_between_cycles_on_request():
    import threading
    woken = threading.Event()
    steps = []
    loop = CycleLoop('test', 3600.0, lambda: steps.append(1), lambda: None,
                     preempt=woken.set)
    loop.start()
    try:
        loop.request_preempt()
        assert woken.wait(2.0), 'preempt did not run before the next (hour-long) period'
        assert steps == [1]                          # and the cycle itself did not run again
    finally:
        loop.stop()
