"""Commands preempt polls: a new velocity command goes on the wire before the next read."""

from __future__ import annotations

import math
import os
import time

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from unit_support import MemoryTransport, shipped_profile
from vfd_ros2.control.controller import ControllerConfig, DriveController
from vfd_ros2.control.loop import CycleLoop
from vfd_ros2.drives.modbus import ModbusDrive
from vfd_ros2.protocol.scaling import VelocityScaling
from vfd_ros2.ros.messages import diagnostic_status

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


def test_a_tripped_watchdog_preempts_a_slow_bus(tmp_path):
    """4 drives at 9600 baud: a cycle takes ~0.6 s, the stop must not wait for it.

    Without preemption the zero setpoint would come 0.5 s + up to a whole cycle after
    the last command; with it, within the timeout plus the exchange in flight.
    """
    import threading
    import time

    from vfd_ros2.control.bus import Bus, parse_bus_config
    from vfd_ros2.sim.model import SimulatedDrive
    from vfd_ros2.sim.rtu_line import SimulatedRtuLine
    profile = shipped_profile('boneng_am')
    sims = [SimulatedDrive(profile, unit) for unit in range(1, 5)]
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine(sims, port, baudrate=9600, emulate_wire_time=True).start()
    bus = Bus(parse_bus_config({
        'bus': {'transport.type': 'modbus_rtu', 'transport.port': port,
                'transport.baudrate': 9600},
        'drives': {f'd{unit}': {'transport.unit_id': unit, 'auto_enable': True,
                                'command_timeout': 0.5, 'drive_comm_timeout': 3.0}
                   for unit in range(1, 5)}}))
    controllers = list(bus.controllers.values())
    bus.start()
    try:
        deadline = time.monotonic() + 15.0
        while not all(s.run_requested for s in sims):
            assert time.monotonic() < deadline, 'drives did not start'
            for controller in controllers:
                controller.command_velocity(1.0)
            time.sleep(0.05)
        last_command = time.monotonic()
        for controller in controllers:
            controller.command_velocity(1.0)
        setpoint = profile.parameter('P07.33').address
        stopped_at: dict[int, float] = {}
        done = threading.Event()

        def zero_written() -> bool:
            for stamp, frame in list(line.received):
                if stamp > last_command and frame[1] == 6 and \
                        int.from_bytes(frame[2:4], 'big') == setpoint and frame[4:6] == b'\0\0':
                    # unit 0: a broadcast, which every drive executes
                    for unit in (range(1, 5) if frame[0] == 0 else (frame[0],)):
                        stopped_at.setdefault(unit, stamp)
            return len(stopped_at) == 4
        deadline = time.monotonic() + 5.0
        while not zero_written():
            assert time.monotonic() < deadline, f'zero setpoints seen: {stopped_at}'
            time.sleep(0.01)
        done.set()
        latencies = sorted(stamp - last_command for stamp in stopped_at.values())
        assert latencies[0] > 0.5, latencies             # not before the timeout ...
        # ... and not a bus cycle after it: every drive tripped at once, so one broadcast
        # frame stops them all (a read of 5 registers in flight + the write: ~60 ms; the
        # rest is slack for a loaded machine, still short of a cycle of four at 9600).
        assert latencies[-1] < 0.5 + 0.2, latencies
        def broadcasts() -> list[bytes]:
            return [frame for stamp, frame in list(line.received)
                    if stamp > last_command and frame[0] == 0]
        deadline = time.monotonic() + 2.0
        while len(broadcasts()) < 2:
            assert time.monotonic() < deadline, broadcasts()
            time.sleep(0.01)
        command = profile.parameter('P07.32').address
        assert [int.from_bytes(frame[2:4], 'big') for frame in broadcasts()] == \
            [setpoint, command]                       # zero setpoint, then the stop
    finally:
        bus.shutdown()
        line.stop()


def test_a_tripped_watchdog_wakes_an_idle_loop(tmp_path):
    """At 2 Hz the loop sleeps ~0.5 s between cycles: the stop must not wait for the next."""
    import time

    from vfd_ros2.control.factory import build_controller
    from vfd_ros2.sim.model import SimulatedDrive
    from vfd_ros2.sim.rtu_line import SimulatedRtuLine
    profile = shipped_profile('boneng_am')
    sim = SimulatedDrive(profile, 1)
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine([sim], port).start()
    controller = build_controller({'transport.port': port, 'auto_enable': True,
                                   'control_rate': 2.0, 'command_timeout': 0.1,
                                   'drive_comm_timeout': 3.0})
    controller.start()
    try:
        deadline = time.monotonic() + 10.0
        while not sim.run_requested:
            assert time.monotonic() < deadline, 'the drive did not start'
            controller.command_velocity(1.0)
            time.sleep(0.05)
        controller.command_velocity(1.0)
        last_command = time.monotonic()
        setpoint = profile.parameter('P07.33').address
        deadline = time.monotonic() + 3.0
        while True:
            stops = [stamp for stamp, frame in list(line.received)
                     if stamp > last_command and frame[1] == 6 and
                     int.from_bytes(frame[2:4], 'big') == setpoint and frame[4:6] == b'\0\0']
            if stops:
                break
            assert time.monotonic() < deadline, 'no zero setpoint'
            time.sleep(0.01)
        # The next cycle is up to 0.5 s away; the watchdog's own moment is 0.1 s.
        assert 0.1 < stops[0] - last_command < 0.1 + 0.15
    finally:
        controller.shutdown()
        line.stop()


def test_one_silent_commander_never_broadcasts_a_stop_to_the_others(tmp_path):
    """Only drive 1's commands stop: the others keep running, no unit-0 frame goes out."""
    import time

    from vfd_ros2.control.bus import Bus, parse_bus_config
    from vfd_ros2.sim.model import SimulatedDrive
    from vfd_ros2.sim.rtu_line import SimulatedRtuLine
    profile = shipped_profile('boneng_am')
    sims = [SimulatedDrive(profile, unit) for unit in (1, 2)]
    port = str(tmp_path / 'line')
    line = SimulatedRtuLine(sims, port).start()
    bus = Bus(parse_bus_config({
        'bus': {'transport.type': 'modbus_rtu', 'transport.port': port},
        'drives': {f'd{unit}': {'transport.unit_id': unit, 'auto_enable': True,
                                'command_timeout': 0.2, 'drive_comm_timeout': 3.0}
                   for unit in (1, 2)}}))
    first, second = bus.controllers.values()
    bus.start()
    try:
        deadline = time.monotonic() + 10.0
        while not all(s.run_requested for s in sims):
            assert time.monotonic() < deadline, 'drives did not start'
            first.command_velocity(1.0)
            second.command_velocity(1.0)
            time.sleep(0.05)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:           # drive 1's commander is gone
            second.command_velocity(1.0)
            time.sleep(0.05)
        assert not sims[0].run_requested and sims[1].run_requested
        assert not any(frame[0] == 0 for _, frame in list(line.received))
        assert bus.broadcast_stops == 0
    finally:
        bus.shutdown()
        line.stop()


def test_realtime_priority_runs_the_loop_thread_under_sched_fifo():
    """A loaded machine must not delay a fast loop's wake-ups: SCHED_FIFO where allowed."""
    seen: list[int] = []
    loop = CycleLoop('rt', 0.01, lambda: seen.append(os.sched_getscheduler(0)), lambda: None,
                     priority=7)
    loop.start()
    try:
        deadline = time.monotonic() + 2.0
        while len(seen) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        loop.stop()
    if loop.notes:      # an unprivileged runner: the refusal must be what is reported
        assert 'realtime_priority 7 refused' in loop.notes[0]
        assert seen[-1] != os.SCHED_FIFO
    else:
        assert seen[-1] == os.SCHED_FIFO
    assert os.sched_getscheduler(0) != os.SCHED_FIFO       # only the loop thread


def test_a_refused_realtime_priority_is_a_diagnostics_warning(monkeypatch):
    def refuse(*_args):
        raise PermissionError(1, 'Operation not permitted')
    monkeypatch.setattr(os, 'sched_setscheduler', refuse)
    transport = MemoryTransport()
    profile = shipped_profile('boneng_am')
    transport.registers[0xE101] = 1
    drive = ModbusDrive(profile, transport, 1, VelocityScaling(gear_ratio=10.0,
                                                               rated_speed_rpm=1330.0))
    controller = DriveController(drive, ControllerConfig(realtime_priority=20,
                                                         apply_commissioning=False))
    controller.start()
    try:
        deadline = time.monotonic() + 2.0
        while not (controller.state.online and controller.state.link_notes) and \
                time.monotonic() < deadline:
            time.sleep(0.01)
        state = controller.state
        notes = state.link_notes
    finally:
        controller.shutdown()
    assert any('realtime_priority 20 refused' in note and 'not permitted' in note
               for note in notes), notes
    status = diagnostic_status(state, 'drive', ever_online=True)
    assert status.level == DiagnosticStatus.WARN
    assert 'realtime_priority 20 refused' in status.message


@pytest.mark.parametrize('enabled_again', [False, True])
def test_a_drive_running_when_the_host_wants_it_running_again_is_no_unexpected_start(
        enabled_again):
    """Enable, disable, enable in quick succession (a service storm).

    The idle command was written, the drive shows the host's own earlier run, and
    the host wants it running again by the time it is read. That was counted and
    logged as a start from elsewhere ("... although the host has it running").
    """
    transport = CommandDuringPoll()
    controller = controller_on(transport)
    controller.intent.enabled = False
    controller.step()                                # connect; idle written
    controller.command_velocity(1.0)                 # fresh commands
    controller.step()                                # idle written all the same (disabled)
    transport.registers[0xE102] = 1                  # P01.02 run: the drive reports running
    controller.intent.enabled = enabled_again        # ~/enable (nothing written yet)
    controller.poll_phase()                          # read before the next command write
    assert controller.state.unexpected_starts == (0 if enabled_again else 1)
