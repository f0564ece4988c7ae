from setuptools import find_packages, setup

package_name = "lsu_common"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["py.typed"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="LSU developers",
    maintainer_email="lsu-dev@example.org",
    description="Helpers every LSU node shares: the node main() runner, table-driven parameters, named QoS "
                "profiles, integer-nanosecond stamps, the sensor_msgs/Image codec and diagnostics.",
    license="Apache-2.0",
    tests_require=["pytest"],
)
