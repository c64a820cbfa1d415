"""The ipmc-ros graph on the real rig over RS-485 (a full ROS 2 install; pip-only:
`ipmc bringup --rig PORT`).

    ros2 launch ipmc_control rig.launch.py port:=/dev/ttyUSB0 model:=/abs/inverse.json
        mode:=hybrid reference:=sine [record:=run1]

The same nodes and parameters as ``ipmc bringup --rig`` (``ipmc_control.launching``).
"""

from ipmc_control.launching import launch_description


def generate_launch_description():
    return launch_description(rig=True)
