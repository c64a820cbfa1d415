"""The ipmc-ros graph on the simulated IPMC (a full ROS 2 install; pip-only: `ipmc bringup --sim`).

    ros2 launch ipmc_control sim.launch.py model:=/abs/inverse.json mode:=hybrid reference:=sine
        (or forward_model:=/abs/fwd.json: a forward model with voltage channels, inverted)
        [lockstep:=true] [record:=run1] [plant_effects:="['creep']"]
        [amplitude_mm:=2.5 frequency_hz:=0.159 value_mm:=1.5 levels_mm:=-2,0,2 hold_s:=5
         range_mm:=-4,2 path:=/abs/ref.csv]

The same nodes and parameters as ``ipmc bringup`` (``ipmc_control.launching``), including the
lock-step listener counts; the reference's settings are checked as bringup checks them.
"""

from ipmc_control.launching import launch_description


def generate_launch_description():
    return launch_description(rig=False)
