"""IPMC rig driver, rig emulator, simulated plant, recorder and data tools (ipmc-ros)."""

__version__ = "0.1.0"
