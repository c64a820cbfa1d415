from glob import glob

from setuptools import find_packages, setup

package_name = "ipmc_model"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="ipmc-ros developers",
    maintainer_email="ipmc-ros@example.org",
    description="Hysteresis models for IPMC actuators: Prandtl-Ishlinskii, LSSVM-NARX, ABC/PSO.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "model_server = ipmc_model.nodes.model_server:main",
            "identify = ipmc_model.identify_cli:identify_main",
            "evaluate = ipmc_model.identify_cli:evaluate_main",
            "diagnose = ipmc_model.diagnose_cli:main",
        ],
        "ipmc.commands": [
            "identify = ipmc_model.identify_cli:identify_main",
            "evaluate = ipmc_model.identify_cli:evaluate_main",
            "diagnose = ipmc_model.diagnose_cli:main",
        ],
    },
)
