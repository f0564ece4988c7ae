from setuptools import find_packages, setup

package_name = "lsu_extract"

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
    description="Sub-pixel laser line extraction (thesis detector and sub-pixel detectors) and the laser_extractor node.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "laser_extractor = lsu_extract.node:main",
        ],
        "lsu.nodes": [
            "laser_extractor = lsu_extract.node:LaserExtractorNode",
        ],
        "lsu.commands": [
            "extract = lsu_extract.cli:register",
        ],
    },
)
