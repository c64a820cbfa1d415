"""Hysteresis models for IPMC actuators (ipmc-ros): Prandtl-Ishlinskii, LSSVM-NARX, ABC, PSO."""
