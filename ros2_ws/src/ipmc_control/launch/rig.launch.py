"""The ipmc-ros graph on the real rig over RS-485 (a full ROS 2 install; pip-only:
`ipmc bringup --rig PORT`).

    ros2 launch ipmc_control rig.launch.py port:=/dev/ttyUSB0 model:=/abs/inverse.json
        mode:=hybrid reference:=sine [record:=run1]
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("port", description="serial device of the RS-485 adapter"),
        DeclareLaunchArgument("model", default_value="", description="inverse model file"),
        DeclareLaunchArgument("forward_model", default_value="",
                              description="forward model file; with voltage channels and no "
                                          "inverse model it is inverted for the feedforward"),
        DeclareLaunchArgument("mode", default_value="hybrid", description="pid|inverse|hybrid"),
        DeclareLaunchArgument("reference", default_value="sine"),
        DeclareLaunchArgument("record", default_value="", description="bag folder to record"),
        Node(package="ipmc_driver", executable="driver", name="driver",
             parameters=[{"port": LaunchConfiguration("port")}]),
        Node(package="ipmc_model", executable="model_server", name="model_server",
             condition=IfCondition(PythonExpression([
                 "'", LaunchConfiguration("model"), "' != '' or '",
                 LaunchConfiguration("forward_model"), "' != ''"])),
             parameters=[{"inverse_model_file": LaunchConfiguration("model"),
                          "model_file": LaunchConfiguration("forward_model")}]),
        Node(package="ipmc_control", executable="controller", name="controller",
             parameters=[{"mode": LaunchConfiguration("mode")}]),
        Node(package="ipmc_control", executable="reference", name="reference",
             parameters=[{"kind": LaunchConfiguration("reference"), "preview_s": 0.02}]),
        Node(package="ipmc_driver", executable="recorder", name="recorder",
             condition=IfCondition(PythonExpression(["'", LaunchConfiguration("record"),
                                                     "' != ''"])),
             parameters=[{"output": LaunchConfiguration("record")}]),
    ])
