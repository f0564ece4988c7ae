from setuptools import find_packages, setup

package_name = "lsu_bringup"

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
    description="The scan_coordinator node, launch files and the lsu command (launch, run, graph introspection, doctor, bags).",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "lsu = lsu_bringup.cli:main",
            "selftest_talker = lsu_bringup.selftest:talker_main",
            "selftest_listener = lsu_bringup.selftest:listener_main",
            "scan_coordinator = lsu_bringup.coordinator:main",
        ],
        # node classes for `lsu run` (all nodes in one process); name = executable name
        "lsu.nodes": [
            "selftest_talker = lsu_bringup.selftest:SelftestTalker",
            "selftest_listener = lsu_bringup.selftest:SelftestListener",
            "scan_coordinator = lsu_bringup.coordinator:ScanCoordinatorNode",
        ],
    },
)
