"""Services answered later from another thread, on both executors the package can spin."""

import threading
import time
import uuid

import pytest
from rclpy.node import Node
from rclpy.qos import QoSProfile
from std_srvs.srv import Trigger

from vfd_ros2.ros.deferred_service import Deferred, create_deferred_service
from vfd_ros2.ros.executable import EXECUTOR_VARIABLE, make_executor, spin_in_background


@pytest.mark.parametrize('executor_name', ['events', 'single'])
def test_an_answer_from_another_thread_reaches_the_caller(ros_context, monkeypatch,
                                                          executor_name):
    monkeypatch.setenv(EXECUTOR_VARIABLE, executor_name)
    executor = make_executor(ros_context)
    name = f'/deferred_{uuid.uuid4().hex[:8]}'
    server = Node('server', context=ros_context)
    calls = []

    def handle(_request, response):
        calls.append(threading.get_ident())
        deferred = Deferred()
        if len(calls) == 1:           # answered immediately: a plain response
            response.success, response.message = True, 'now'
            return response

        def later():
            time.sleep(0.05)
            response.success, response.message = True, f'later {len(calls)}'
            deferred.complete(response)
        threading.Thread(target=later, daemon=True).start()
        return deferred

    create_deferred_service(server, Trigger, name, handle, QoSProfile(depth=10))
    client_node = Node('client', context=ros_context)
    client = client_node.create_client(Trigger, name)
    executor.add_node(server)
    executor.add_node(client_node)
    spin = spin_in_background(executor, ros_context)
    try:
        assert client.wait_for_service(5.0)
        answers = []
        for _ in range(3):
            future = client.call_async(Trigger.Request())
            deadline = time.monotonic() + 5.0
            while not future.done() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert future.done(), f'no answer on the {executor_name} executor'
            answers.append(future.result().message)
        assert answers == ['now', 'later 2', 'later 3']
    finally:
        spin.stop()
        executor.shutdown(timeout_sec=1.0)
        server.destroy_node()
        client_node.destroy_node()


def test_a_deferred_answer_is_sent_once_whichever_comes_first():
    sent = []
    early = Deferred()
    early.complete('answer')                  # done before the executor handed it over
    early._attach(sent.append)  # noqa: SLF001
    late = Deferred()
    late._attach(sent.append)  # noqa: SLF001
    late.complete('second')
    late.complete('again')                    # a second completion is ignored
    assert sent == ['answer', 'second']


def test_an_unknown_executor_name_is_refused(monkeypatch):
    monkeypatch.setenv(EXECUTOR_VARIABLE, 'multi')
    with pytest.raises(ValueError, match='expected events or single'):
        make_executor()
