"""The ipmc-ros graph on the simulated IPMC (a full ROS 2 install; pip-only: `ipmc bringup --sim`).

    ros2 launch ipmc_control sim.launch.py model:=/abs/inverse.json mode:=hybrid reference:=sine
        (or forward_model:=/abs/fwd.json: a forward model with voltage channels, inverted)
        [lockstep:=true] [record:=run1] [plant_effects:="['creep']"]
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    model = LaunchConfiguration("model")
    lockstep = LaunchConfiguration("lockstep")
    sim_time = PythonExpression(["'", lockstep, "' == 'true'"])
    return LaunchDescription([
        DeclareLaunchArgument("model", default_value="", description="inverse model file"),
        DeclareLaunchArgument("forward_model", default_value="",
                              description="forward model file; with voltage channels and no "
                                          "inverse model it is inverted for the feedforward"),
        DeclareLaunchArgument("mode", default_value="hybrid", description="pid|inverse|hybrid"),
        DeclareLaunchArgument("reference", default_value="sine",
                              description="constant|sine|random|steps|file"),
        DeclareLaunchArgument("lockstep", default_value="false",
                              description="lock-step clock, faster than real time"),
        DeclareLaunchArgument("record", default_value="", description="bag folder to record"),
        Node(package="ipmc_driver", executable="sim_plant", name="sim_plant", parameters=[{
            "clock_mode": PythonExpression(["'lockstep' if '", lockstep,
                                            "' == 'true' else 'realtime'"]),
            # lock-step: time starts once the controller's stamped commands have matched.
            "lockstep_min_command_publishers": PythonExpression(
                ["1 if '", lockstep, "' == 'true' else 0"])}]),
        Node(package="ipmc_model", executable="model_server", name="model_server",
             condition=IfCondition(PythonExpression([
                 "'", LaunchConfiguration("model"), "' != '' or '",
                 LaunchConfiguration("forward_model"), "' != ''"])),
             parameters=[{"inverse_model_file": model, "use_sim_time": sim_time,
                          "model_file": LaunchConfiguration("forward_model")}]),
        Node(package="ipmc_control", executable="controller", name="controller",
             parameters=[{"mode": LaunchConfiguration("mode"), "use_sim_time": sim_time,
                          "trigger": PythonExpression(["'measurement' if '", lockstep,
                                                       "' == 'true' else 'timer'"])}]),
        Node(package="ipmc_control", executable="reference", name="reference",
             parameters=[{"kind": LaunchConfiguration("reference"), "preview_s": 0.02,
                          "use_sim_time": sim_time}]),
        Node(package="ipmc_driver", executable="recorder", name="recorder",
             condition=IfCondition(PythonExpression(["'", LaunchConfiguration("record"),
                                                     "' != ''"])),
             parameters=[{"output": LaunchConfiguration("record"), "use_sim_time": sim_time}]),
    ])
