from glob import glob

from setuptools import find_packages, setup

package_name = "leapnbv_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*")),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    description="Launch files, deployed parameters and the graph runner for the LEAP-NBV node set.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "power_node = leapnbv_bringup.nodes.power_node:main",
            "graph_monitor = leapnbv_bringup.graph_monitor:main",
            "lifecycle_manager = leapnbv_bringup.lifecycle_manager:main",
        ],
    },
)
