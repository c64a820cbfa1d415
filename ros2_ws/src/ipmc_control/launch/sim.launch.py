"""The ipmc-ros graph on the simulated IPMC (a full ROS 2 install; pip-only: `ipmc bringup --sim`).

    ros2 launch ipmc_control sim.launch.py model:=/abs/inverse.json mode:=hybrid reference:=sine
        (or forward_model:=/abs/fwd.json: a forward model with voltage channels, inverted)
        [lockstep:=true] [record:=run1] [plant_effects:="['creep']"]

The same nodes and parameters as ``ipmc bringup`` (``ipmc_control.launching``), including the
lock-step listener counts.
"""

from ipmc_control.launching import launch_description


def generate_launch_description():
    return launch_description(rig=False)
