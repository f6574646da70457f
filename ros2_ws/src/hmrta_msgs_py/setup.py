from setuptools import find_packages, setup

package_name = "hmrta_msgs_py"

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
    maintainer="hmrta developers",
    maintainer_email="hmrta@example.com",
    description="HMRTA message layer: payload codecs, topic names and QoS profiles",
    license="Apache-2.0",
)
