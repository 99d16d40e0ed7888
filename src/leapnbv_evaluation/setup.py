from setuptools import find_packages, setup

package_name = "leapnbv_evaluation"

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
    description="Closed-loop evaluation on synthetic scenes: evaluator, metrics, benchmark sets, reports, demo.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "evaluate = leapnbv_evaluation.cli:main",
            "demo = leapnbv_evaluation.demo:main",
        ],
    },
)
