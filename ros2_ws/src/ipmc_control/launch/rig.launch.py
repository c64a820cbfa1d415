"""The ipmc-ros graph on the real rig over RS-485 (a full ROS 2 install; pip-only:
`ipmc bringup --rig PORT`).

    ros2 launch ipmc_control rig.launch.py port:=/dev/ttyUSB0 model:=/abs/inverse.json
        mode:=hybrid reference:=sine [amplitude_mm:=2.5 frequency_hz:=0.159 value_mm:=1.5
        levels_mm:=-2,0,2 hold_s:=5 range_mm:=-4,2 path:=/abs/ref.csv] [record:=run1]

The same nodes and parameters as ``ipmc bringup --rig`` (``ipmc_control.launching``); the
reference's settings are checked against the model's identified range as bringup checks them.
"""

from ipmc_control.launching import launch_description


def generate_launch_description():
    return launch_description(rig=True)
