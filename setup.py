"""Setuptools metadata for the hand-written vfd_ros2 Python package.

The package is built with ament_cmake (see CMakeLists.txt) because it generates
ROS interfaces; ament_python_install_package() installs this Python package and
the console_scripts of setup.cfg next to the generated vfd_ros2.msg/.srv.
This file keeps the same metadata for tools that expect a setup.py.
"""
from setuptools import find_packages, setup

setup(
    name='vfd_ros2',
    version='0.1.0',
    packages=find_packages(include=('vfd_ros2', 'vfd_ros2.*')),
    package_data={'vfd_ros2': ['profiles/*.yaml']},
    zip_safe=False,
)
