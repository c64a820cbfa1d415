import subprocess
import sys


def test_import_core_leaves_rclpy_out():
    code = (
        "import sys\n"
        "import ipmc_model.metrics, ipmc_model.play, ipmc_model.pso, ipmc_model.bee_colony\n"
        "import ipmc_model.lssvm, ipmc_model.narx, ipmc_model.persistence, ipmc_model.tuning\n"
        "import ipmc_model.identify_cli, ipmc_model.errors\n"
        "assert 'rclpy' not in sys.modules, 'rclpy imported'\n"
        "assert 'matplotlib' not in sys.modules, 'matplotlib imported eagerly'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
