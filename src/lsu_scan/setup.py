from setuptools import find_packages, setup

package_name = "lsu_scan"

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
    description="The scan_coordinator node (stop-snap scans through the /lsu/scan action), its scan plan and laser guard, and LsuScanner, the Python API.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": ["scan_coordinator = lsu_scan.coordinator:main"],
        "lsu.nodes": ["scan_coordinator = lsu_scan.coordinator:ScanCoordinatorNode"],
        "lsu.commands": ["scan = lsu_scan.scanner:register"],
    },
)
