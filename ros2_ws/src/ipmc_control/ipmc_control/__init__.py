"""Hybrid inverse-feedforward + PID control of IPMC actuators (ipmc-ros)."""
