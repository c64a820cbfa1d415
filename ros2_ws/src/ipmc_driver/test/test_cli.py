"""The ``ipmc`` dispatcher."""

from __future__ import annotations

import os
import subprocess
import sys

from ipmc_driver.cli import BLAS_THREADS, limit_blas_threads


def test_blas_threads_are_limited_unless_the_user_set_them():
    env = {}
    limit_blas_threads(env)
    assert env["OPENBLAS_NUM_THREADS"] == BLAS_THREADS
    env = {"OPENBLAS_NUM_THREADS": "2"}
    limit_blas_threads(env)
    assert env["OPENBLAS_NUM_THREADS"] == "2"


def test_a_command_runs_with_the_limit_before_numpy_loads():
    """OpenBLAS reads the variable when NumPy loads: the dispatcher sets it first."""
    code = ("import sys, os; from ipmc_driver import cli; assert 'numpy' not in sys.modules; "
            "cli.limit_blas_threads(); print(os.environ['OPENBLAS_NUM_THREADS'])")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == BLAS_THREADS
