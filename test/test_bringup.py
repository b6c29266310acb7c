"""Bringup logic used by the launch files and the demo (no processes started here)."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import pytest
import yaml

from vfd_ros2.apps.bringup import (
    DEFAULT_DEMO_DIR,
    DEFAULT_SIM_DIR,
    NodeSpec,
    drive_spec,
    lifecycle_arguments,
    sim_agv,
    sim_agv_bus,
    sim_wheels,
)
from vfd_ros2.control.bus import parse_bus_config
from vfd_ros2.control.settings import SETTINGS
from vfd_ros2.sim.node import parse_initial_values

LAUNCH_DIR = Path(__file__).resolve().parents[1] / 'launch'


def test_sim_wheels_pairs_a_simulator_with_a_driver_per_wheel(tmp_path):
    specs = sim_wheels(directory=str(tmp_path))
    assert [s.executable for s in specs] == ['sim_drive', 'drive_node'] * 2
    sims, drivers = specs[0::2], specs[1::2]
    for sim, driver in zip(sims, drivers):
        assert sim.namespace == driver.namespace
        assert sim.parameters['port'] == driver.parameters['transport.port']
        assert driver.parameters['transport.port'].startswith(str(tmp_path))
    assert [d.parameters['invert_direction'] for d in drivers] == [False, True]
    assert {d.fully_qualified_name for d in drivers} == {'/agv/left_wheel/drive',
                                                         '/agv/right_wheel/drive'}
    settings = {s.name for s in SETTINGS}
    for driver in drivers:
        assert set(driver.parameters) - settings <= {'transport.port'}


def test_sim_initial_values_are_valid_for_the_profile():
    from vfd_ros2.profiles import load_profile
    profile = load_profile('boneng_am')
    for spec in sim_wheels()[0::2]:
        for code, value in parse_initial_values(spec.parameters['initial_values']).items():
            assert profile.parameter(code).to_raw(value) >= 0


def test_params_file_and_command_line(tmp_path):
    spec = NodeSpec('drive_node', 'drive', '/agv/left_wheel', {'gear_ratio': 12.5})
    path = spec.write_params_file(tmp_path)
    assert yaml.safe_load(path.read_text()) == {
        '/agv/left_wheel/drive': {'ros__parameters': {'gear_ratio': 12.5}}}
    assert spec.command(path) == ['drive_node', '--ros-args', '-r', '__ns:=/agv/left_wheel',
                                  '-r', '__node:=drive', '--params-file', str(path)]


def test_drive_spec_refuses_unknown_parameters():
    with pytest.raises(ValueError, match='gear_ration'):
        drive_spec('/x', {'gear_ration': 10.0})
    assert drive_spec('/x', {'transport.anything': 1}).parameters == {'transport.anything': 1}


def test_parse_initial_values_rejects_garbage():
    assert parse_initial_values(['B04.02=1.5', ' acceleration_time = 2 ']) == {
        'B04.02': 1.5, 'acceleration_time': 2.0}
    with pytest.raises(ValueError, match='CODE=VALUE'):
        parse_initial_values(['B04.02'])
    with pytest.raises(ValueError):
        parse_initial_values(['B04.02=fast'])


def _fake_launch_modules(monkeypatch):
    """Minimal stand-ins for launch / launch_ros (not installable from PyPI here)."""
    class Action:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Action):
        def perform(self, context):
            return context[self.args[0]]

    modules = {
        'launch': {'LaunchDescription': lambda actions: list(actions)},
        'launch.actions': {'DeclareLaunchArgument': Action, 'OpaqueFunction': Action,
                           'SetEnvironmentVariable': Action, 'Shutdown': Action,
                           'LogInfo': Action},
        'launch.conditions': {'IfCondition': Action},
        'launch.substitutions': {'LaunchConfiguration': LaunchConfiguration},
        'launch_ros': {},
        'launch_ros.actions': {'Node': Action},
    }
    for name, attributes in modules.items():
        module = types.ModuleType(name)
        module.__dict__.update(attributes)
        monkeypatch.setitem(sys.modules, name, module)
    return Action


def _load_launch_file(name):
    spec = importlib.util.spec_from_file_location(name.replace('.', '_'), LAUNCH_DIR / name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


PLAIN = {'managed': 'false', 'autostart': 'true'}


def test_demo_launch_file_builds_the_bringup_nodes(monkeypatch):
    Action = _fake_launch_modules(monkeypatch)
    module = _load_launch_file('demo.launch.py')
    actions = module.generate_launch_description()
    opaque = next(a for a in actions if a.kwargs.get('function'))
    nodes = opaque.kwargs['function']({'directory': '/tmp/x', **PLAIN})
    expected = sim_wheels(directory='/tmp/x')
    assert [(n.kwargs['executable'], n.kwargs['namespace'], n.kwargs['parameters'])
            for n in nodes] == [(s.executable, s.namespace, [s.parameters]) for s in expected]
    assert all(n.kwargs['arguments'] == [] for n in nodes)
    demo = [a for a in actions if isinstance(a, Action) and a.kwargs.get('executable') == 'demo']
    assert demo and demo[0].kwargs['arguments'] == ['--attach']
    # The profile's end ends the launch (the processes stayed up until Ctrl-C: outside
    # audit with the real ros2 launch); a failed demo leaves them up, saying so.
    after = demo[0].kwargs['on_exit']
    [ended] = after(types.SimpleNamespace(returncode=0), None)
    assert ended.kwargs == {'reason': 'the demo profile ended'}
    [failed] = after(types.SimpleNamespace(returncode=1), None)
    assert 'the demo failed (exit code 1)' in failed.kwargs['msg']
    # The demo refuses to run unless DDS stays on this machine: the launch file says so
    # first (on an apt machine nothing else sets it), before any process starts.
    assert actions[0].args == ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    # Piped launch output carries no ANSI colour codes: no node pretends to be on a tty.
    assert all(a.kwargs.get('emulate_tty') is False for a in [*nodes, *demo])
    defaults = {a.args[0]: a.kwargs.get('default_value') for a in actions
                if a.args and isinstance(a.args[0], str)}
    assert defaults['directory'] == DEFAULT_DEMO_DIR != DEFAULT_SIM_DIR
    assert (defaults['managed'], defaults['autostart']) == ('false', 'true')

    managed = opaque.kwargs['function']({'directory': '/tmp/x', 'managed': 'true',
                                         'autostart': 'false'})
    assert {n.kwargs['executable']: n.kwargs['arguments'] for n in managed} == {
        'sim_drive': [], 'drive_node': ['--managed']}


def test_lifecycle_arguments():
    assert lifecycle_arguments('false', 'true') == ()
    assert lifecycle_arguments('True', 'true') == ('--managed', '--autostart')
    assert lifecycle_arguments(True, False) == ('--managed',)
    with pytest.raises(ValueError, match='yes'):
        lifecycle_arguments('yes', 'true')
    spec = NodeSpec('drive_node', 'drive', '/a').managed('true', 'true')
    assert spec.command(Path('p.yaml'))[:3] == ['drive_node', '--managed', '--autostart']


def test_drive_launch_file_passes_the_params_file(monkeypatch):
    _fake_launch_modules(monkeypatch)
    actions = _load_launch_file('drive.launch.py').generate_launch_description()
    opaque = next(a for a in actions if a.kwargs.get('function'))
    context = {'params_file': '/p/drive.yaml', 'name': 'drive', 'namespace': '/agv/left',
               'managed': 'true', 'autostart': 'true'}
    node = opaque.kwargs['function'](context)[0]
    assert node.kwargs['package'] == 'vfd_ros2' and node.kwargs['executable'] == 'drive_node'
    assert node.kwargs['parameters'] == ['/p/drive.yaml']
    assert node.kwargs['arguments'] == ['--managed', '--autostart']
    assert node.kwargs['emulate_tty'] is False


@pytest.mark.parametrize('path', sorted((LAUNCH_DIR.parent / 'config').glob('*_drive.yaml')),
                         ids=lambda p: p.name)
def test_example_configs_build_a_controller(path):
    """Every shipped example parameter file is valid for drive_node (nothing unknown)."""
    from vfd_ros2.control.factory import build_controller
    from vfd_ros2.transports import load_transport_class
    values = yaml.safe_load(path.read_text())['/**']['ros__parameters']
    known = {s.name for s in SETTINGS} | {
        f'transport.{p.name}' for p in load_transport_class(values['transport.type']).parameters}
    assert set(values) <= known, set(values) - known
    controller = build_controller(values)
    assert controller.drive.profile.name == values['drive.profile']


def test_sim_agv_puts_both_drives_on_one_line_behind_one_bus_node(tmp_path):
    specs = {spec.executable: spec for spec in sim_agv(directory=str(tmp_path))}
    assert set(specs) == {'sim_drive', 'bus_node', 'diff_drive'}
    bus = parse_bus_config(sim_agv_bus(str(tmp_path)))
    assert specs['sim_drive'].parameters['port'] == bus.settings['transport.port']
    assert specs['sim_drive'].parameters['unit_ids'] == [
        d.settings['transport.unit_id'] for d in bus.drives]
    assert specs['bus_node'].parameters['config_file'] == str(tmp_path / 'bus.yaml')
    diff = specs['diff_drive'].parameters
    namespaces = [d.namespace for d in bus.drives]
    assert diff['left_wheel_command_topic'] == f'{namespaces[0]}/drive/velocity_command'
    assert diff['right_wheel_status_topic'] == f'{namespaces[1]}/drive/status'
    assert diff['left_wheel_joint_states_topic'] == f'{namespaces[0]}/joint_states'
    assert diff['use_stamped_vel'] is True
    assert [d.settings['invert_direction'] for d in bus.drives] == [False, True]


def test_sim_agv_launch_file_writes_the_bus_file(monkeypatch, tmp_path):
    _fake_launch_modules(monkeypatch)
    actions = _load_launch_file('sim_agv.launch.py').generate_launch_description()
    opaque = next(a for a in actions if a.kwargs.get('function'))
    nodes = opaque.kwargs['function']({'directory': str(tmp_path), **PLAIN})
    assert [n.kwargs['executable'] for n in nodes] == ['sim_drive', 'bus_node', 'diff_drive']
    written = parse_bus_config(yaml.safe_load((tmp_path / 'bus.yaml').read_text()))
    assert written == parse_bus_config(sim_agv_bus(str(tmp_path)))
    managed = opaque.kwargs['function']({'directory': str(tmp_path), 'managed': 'true',
                                         'autostart': 'true'})
    assert [n.kwargs['arguments'] for n in managed] == [[], ['--managed', '--autostart'], []]


def test_bus_launch_file(monkeypatch):
    _fake_launch_modules(monkeypatch)
    actions = _load_launch_file('bus.launch.py').generate_launch_description()
    opaque = next(a for a in actions if a.kwargs.get('function'))
    node = opaque.kwargs['function']({'config_file': '/c/bus.yaml', 'name': 'bus',
                                      'namespace': '/', 'joint_commands_topic': '/cmd',
                                      'joint_states_topic': '', **PLAIN})[0]
    assert node.kwargs['executable'] == 'bus_node'
    assert node.kwargs['parameters'][0]['config_file'] == '/c/bus.yaml'
    assert node.kwargs['parameters'][0]['joint_commands_topic'] == '/cmd'
    assert node.kwargs['parameters'][0]['joint_states_topic'] == ''
    assert node.kwargs['arguments'] == [] and node.kwargs['emulate_tty'] is False


def test_aggregator_yaml_groups_the_diagnostic_names():
    from vfd_ros2.ros.messages import bus_diagnostic_name, drive_diagnostic_name
    path = LAUNCH_DIR.parent / 'config' / 'diagnostics_aggregator.yaml'
    analyzers = yaml.safe_load(path.read_text())['analyzers']['ros__parameters']
    drives = analyzers['traction_drives']['contains']
    buses = analyzers['field_buses']['contains']
    drive = drive_diagnostic_name('/agv/left_wheel/drive')
    bus = bus_diagnostic_name('/agv/bus', 'rs485_0')
    assert drive == 'agv/left_wheel/drive: drive'
    assert any(p in drive for p in drives) and not any(p in drive for p in buses)
    assert any(p in bus for p in buses) and not any(p in bus for p in drives)


def test_readme_config_paths_work_from_anywhere():
    """The README's --params-file / config_file paths: installed files, not relative paths."""
    import re
    readme = (LAUNCH_DIR.parent / 'README.md').read_text()
    installed = re.findall(r'\$CONFIG/([\w./-]+\.yaml)', readme)
    assert installed, 'the README shows the installed config files'
    for name in installed:
        assert (LAUNCH_DIR.parent / 'config' / name).is_file(), name
    relative = re.findall(r'(?:--params-file|config_file:=|params_file:=)\s*([^\s$<][^\s]*)',
                          readme)
    assert not relative, f'paths that depend on the working directory: {relative}'


def test_a_mistyped_option_is_refused_not_taken_for_a_plain_node():
    """--manged used to start a plain node, enabled at once where auto_enable is set."""
    from vfd_ros2.errors import ParameterError
    from vfd_ros2.ros.managed import parse_options
    assert parse_options(['drive_node', '--managed', '--ros-args', '-p', 'x:=1']).managed
    with pytest.raises(ParameterError, match='unknown argument.* --manged'):
        parse_options(['drive_node', '--manged', '--ros-args', '-p', 'x:=1'])
    with pytest.raises(ParameterError, match='give --managed too'):
        parse_options(['drive_node', '--autostart', '--ros-args', '-p', 'x:=1'])
    # nodes without options of their own refuse any too
    from vfd_ros2.ros.executable import only_ros_arguments
    only_ros_arguments(['diff_drive', '--ros-args', '-p', 'x:=1'])
    with pytest.raises(ParameterError, match='unknown argument.* --managed'):
        only_ros_arguments(['sim_drive', '--managed', '--ros-args', '-p', 'x:=1'])


def test_a_params_file_that_does_not_parse_is_one_line_not_a_traceback(tmp_path, capsys):
    from vfd_ros2.ros.drive_node import main
    path = tmp_path / 'drive.yaml'
    path.write_text('/**:\n\tros__parameters:\n    max_velocity: 1.0\n')       # a tab
    assert main(['drive_node', '--ros-args', '--params-file', str(path)]) == 1
    out = capsys.readouterr().out
    assert out.startswith('drive_node: cannot start (check --ros-args and --params-file)')
    assert 'Traceback' not in out


def test_loop_errors_are_logged_once_with_a_traceback_then_counted(caplog):
    from vfd_ros2.control.loop import CycleLoop

    def broken() -> None:
        raise struct_error('argument out of range')
    struct_error = type('error', (Exception,), {})
    loop = CycleLoop('d', 0.02, broken, lambda: None)
    with caplog.at_level('ERROR', logger='vfd_ros2.control.loop'):
        for _ in range(170):
            loop._guarded(broken)
    assert loop.errors == 170
    assert len(caplog.records) == 1 and caplog.records[0].exc_info is not None
    loop._tell_repeats(at_end=True)      # as the loop ends: the repeats are told, not lost
    assert len(caplog.records) == 2 and '169 more times' in caplog.records[1].getMessage()


def test_a_loop_failing_every_step_still_tells_another_errors_repeats(caplog, monkeypatch):
    """Error B repeated, then only error A came (no good step): B's count stayed untold."""
    import types

    from vfd_ros2.control import loop as loop_module
    from vfd_ros2.control.loop import LOOP_ERROR_LOG_PERIOD, CycleLoop
    now = [1000.0]
    monkeypatch.setattr(loop_module, 'time', types.SimpleNamespace(monotonic=lambda: now[0]))

    def fail_a() -> None:
        raise KeyError('a')

    def fail_b() -> None:
        raise ValueError('b')
    loop = CycleLoop('d', 0.02, fail_a, lambda: None)
    with caplog.at_level('ERROR', logger='vfd_ros2.control.loop'):
        for _ in range(3):
            loop._guarded(fail_b)
        now[0] += LOOP_ERROR_LOG_PERIOD + 1
        loop._guarded(fail_a)           # A's first: told in full
        loop._guarded(fail_a)           # a repeat of A: B's two repeats are due by now
    assert any('loop error again (2 more times, ValueError' in r.getMessage()
               for r in caplog.records), [r.getMessage() for r in caplog.records]
