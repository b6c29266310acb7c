"""The suite's leak check fails a test that leaves a thread or a file descriptor behind."""

from __future__ import annotations

from pathlib import Path

pytest_plugins = ['pytester']

CONFTEST = (Path(__file__).parent / 'conftest.py').read_text(encoding='utf-8')


def test_a_leaked_thread_and_file_fail_the_test(pytester):
    pytester.makeconftest(CONFTEST)
    pytester.makepyfile(test_inner="""
import os
import threading

import pytest

stop = threading.Event()
kept = []


@pytest.fixture(scope='module', autouse=True)
def tidy_up_after_the_check():
    yield                   # the leak check of each test runs before this
    stop.set()
    for fd in kept:
        os.close(fd)


def test_leaks_a_thread():
    threading.Thread(target=stop.wait, name='forgotten', daemon=True).start()


def test_leaks_a_file(tmp_path):
    kept.append(os.open(tmp_path / 'kept-open', os.O_CREAT | os.O_RDONLY))


def test_cleans_up():
    thread = threading.Thread(target=lambda: None)
    thread.start()
    thread.join()
""")
    result = pytester.runpytest_inprocess('-p', 'no:cacheprovider')
    result.assert_outcomes(passed=3, errors=2)
    result.stdout.fnmatch_lines(['*test_leaks_a_thread leaked threads*forgotten*',
                                 '*test_leaks_a_file leaked*kept-open*'])
