from setuptools import find_packages, setup

package_name = "leapnbv_bags"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    description="Reading and writing rosbag2 MCAP bags of the graph's topics (no ROS runtime needed).",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
        ],
    },
)
