"""The ipmc-ros graph on the simulated IPMC (a full ROS 2 install; pip-only: `ipmc bringup --sim`).

    ros2 launch ipmc_control sim.launch.py model:=/abs/inverse.json mode:=hybrid reference:=sine
        (or forward_model:=/abs/fwd.json: a forward model with voltage channels, inverted)
        [lockstep:=true] [record:=run1] [plant_effects:="['creep']"]

The nodes and their parameters come from ``ipmc_control.bringup.launch_specs``: the same graph
as ``ipmc bringup``, including the lock-step listener counts.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

ARGUMENTS = [
    ("model", "", "feedforward model file: inverse, or forward with voltage channels"),
    ("forward_model", "", "forward model file; alone it is inverted for the feedforward, "
                          "beside an inverse model it serves predictions and the residual"),
    ("mode", "hybrid", "pid|inverse|hybrid"),
    ("reference", "sine", "constant|sine|random|steps|file"),
    ("lockstep", "false", "lock-step clock, faster than real time"),
    ("record", "", "bag folder to record"),
    ("plant_effects", "", "simulated plant effects, e.g. \"['creep']\" or creep,drift"),
]


def _nodes(context):
    from ipmc_control.bringup import launch_specs

    args = {name: LaunchConfiguration(name).perform(context) for name, _, _ in ARGUMENTS}
    return [Node(package=s.package, executable=s.executable, name=s.name,
                 parameters=[s.params], output="screen")
            for s in launch_specs(args, rig=False)]


def generate_launch_description():
    return LaunchDescription([
        *(DeclareLaunchArgument(name, default_value=default, description=text)
          for name, default, text in ARGUMENTS),
        OpaqueFunction(function=_nodes),
    ])
