from glob import glob

from setuptools import find_packages, setup

package_name = "ipmc_driver"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["data/*.yaml"]},
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
    description="IPMC rig driver (RS-485), rig emulator, simulated plant, recorder, data tools.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "ipmc = ipmc_driver.cli:main",
            "sim_plant = ipmc_driver.nodes.sim_plant:main",
            "recorder = ipmc_driver.nodes.recorder:main",
            "driver = ipmc_driver.nodes.driver:main",
            "rig_emulator = ipmc_driver.emulator:main",
            "characterize = ipmc_driver.characterize:main",
        ],
        # Subcommands of the single `ipmc` console script; every package adds its own.
        "ipmc.commands": [
            "characterize = ipmc_driver.characterize:main",
            "simulate = ipmc_driver.simulate_cli:main",
            "bag-recover = ipmc_driver.bagio:recover_main",
            "export = ipmc_driver.dataio:export_main",
            "rig-emulator = ipmc_driver.emulator:main",
        ],
    },
)
