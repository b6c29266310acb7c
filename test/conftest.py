"""Test-wide setup: DDS stays on loopback, or nothing runs."""

import os

import pytest

if os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE') != 'LOCALHOST':
    pytest.exit(
        'ROS_AUTOMATIC_DISCOVERY_RANGE must be LOCALHOST: DDS discovery must not leave this '
        'machine. Run the tests with scripts/test (it sets it), or export it yourself.',
        returncode=4)

pytest_plugins = ['harness']
