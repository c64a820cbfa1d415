from glob import glob

from setuptools import find_packages, setup

package_name = "ipmc_control"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="ipmc-ros developers",
    maintainer_email="ipmc-ros@example.org",
    description="Hybrid inverse-feedforward + PID control of IPMC actuators.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "controller = ipmc_control.nodes.controller:main",
            "reference = ipmc_control.nodes.reference:main",
            "excitation = ipmc_control.nodes.excitation:main",
            "track = ipmc_control.track_cli:main",
            "bringup = ipmc_control.bringup:main",
        ],
        "ipmc.commands": [
            "track = ipmc_control.track_cli:main",
            "bringup = ipmc_control.bringup:main",
            "demo = ipmc_control.demo:main",
            "investigate = ipmc_control.investigate:main",
        ],
    },
)
