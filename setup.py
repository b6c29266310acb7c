"""Setuptools metadata for the hand-written vfd_ros2 Python package.

The package is built with ament_cmake because it generates ROS interfaces, and
CMakeLists.txt installs it: the hand-written modules go next to the generated
vfd_ros2.msg/.srv (install(DIRECTORY)), and one launcher per console_scripts
entry of setup.cfg goes to lib/vfd_ros2 (the only part of setup.cfg the build
reads). This file keeps the same metadata for tools that expect a setup.py.
"""
from setuptools import find_packages, setup

setup(
    name='vfd_ros2',
    version='0.1.0',
    packages=find_packages(include=('vfd_ros2', 'vfd_ros2.*')),
    package_data={'vfd_ros2': ['profiles/*.yaml']},
    zip_safe=False,
)
