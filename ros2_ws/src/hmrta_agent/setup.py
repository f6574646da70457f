from glob import glob

from setuptools import find_packages, setup

package_name = "hmrta_agent"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="hmrta developers",
    maintainer_email="hmrta@example.com",
    description="HMRTA agent node: one decentralised decision maker per robot",
    license="Apache-2.0",
    entry_points={"console_scripts": ["agent_node = hmrta_agent.entry:agent_node"]},
)
