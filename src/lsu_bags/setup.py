from setuptools import find_packages, setup

package_name = "lsu_bags"

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
    description="Bags (rosbags typestore, reader, writer, player, recorder), message introspection and the lsu bag commands; no rclpy at import.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "lsu.commands": ["bag = lsu_bags.bag_cli:register"],
    },
)
