"""The ipmc-ros graph on the real rig over RS-485 (a full ROS 2 install; pip-only:
`ipmc bringup --rig PORT`).

    ros2 launch ipmc_control rig.launch.py port:=/dev/ttyUSB0 model:=/abs/inverse.json
        mode:=hybrid reference:=sine [record:=run1]

The nodes and their parameters come from ``ipmc_control.bringup.launch_specs``: the same graph
as ``ipmc bringup --rig``.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

ARGUMENTS = [
    ("port", None, "serial device of the RS-485 adapter"),
    ("model", "", "feedforward model file: inverse, or forward with voltage channels"),
    ("forward_model", "", "forward model file; alone it is inverted for the feedforward, "
                          "beside an inverse model it serves predictions and the residual"),
    ("mode", "hybrid", "pid|inverse|hybrid"),
    ("reference", "sine", "constant|sine|random|steps|file"),
    ("record", "", "bag folder to record"),
]


def _nodes(context):
    from ipmc_control.bringup import launch_specs

    args = {name: LaunchConfiguration(name).perform(context) for name, _, _ in ARGUMENTS}
    return [Node(package=s.package, executable=s.executable, name=s.name,
                 parameters=[s.params], output="screen")
            for s in launch_specs(args, rig=True)]


def generate_launch_description():
    return LaunchDescription([
        *(DeclareLaunchArgument(name, description=text) if default is None else
          DeclareLaunchArgument(name, default_value=default, description=text)
          for name, default, text in ARGUMENTS),
        OpaqueFunction(function=_nodes),
    ])
