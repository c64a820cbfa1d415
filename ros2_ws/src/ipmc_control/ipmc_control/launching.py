"""The launch descriptions of ``launch/sim.launch.py`` and ``launch/rig.launch.py`` (a full ROS 2
install: ``launch`` and ``launch_ros`` are not on PyPI; pip-only, use ``ipmc bringup``).

The nodes and their parameters come from :func:`ipmc_control.bringup.launch_specs`: the same
graph as ``ipmc bringup``.
"""

from __future__ import annotations

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from ipmc_control.bringup import launch_arguments, launch_specs


def launch_description(*, rig: bool) -> LaunchDescription:
    """Declared arguments, then the graph's nodes built from their values at launch time."""

    def nodes(context):
        args = {name: LaunchConfiguration(name).perform(context)
                for name, _, _ in launch_arguments(rig=rig)}
        return [Node(package=s.package, executable=s.executable, name=s.name,
                     parameters=[s.params], output="screen")
                for s in launch_specs(args, rig=rig)]

    return LaunchDescription([
        *(DeclareLaunchArgument(name, description=text) if default is None else
          DeclareLaunchArgument(name, default_value=default, description=text)
          for name, default, text in launch_arguments(rig=rig)),
        OpaqueFunction(function=nodes),
    ])
