from glob import glob

from setuptools import find_packages, setup

package_name = "hmrta_coordinator"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="hmrta developers",
    maintainer_email="hmrta@example.com",
    description="HMRTA task board, simulated robots and mission launcher",
    license="Apache-2.0",
    entry_points={"console_scripts": [
        "task_board = hmrta_coordinator.entry:task_board",
        "sim_robot = hmrta_coordinator.entry:sim_robot",
        "mission = hmrta_coordinator.entry:mission",
        "hmrta-mission = hmrta_coordinator.entry:mission",
        "hmrta-task = hmrta_coordinator.entry:task_cli",
        "recorder = hmrta_coordinator.entry:recorder",
    ]},
)
