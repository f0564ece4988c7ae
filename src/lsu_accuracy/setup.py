from setuptools import find_packages, setup

package_name = "lsu_accuracy"

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
    description="The accuracy study: extraction, matching, meshing and smoothing against renderer ground truth or recorded board bags (lsu accuracy).",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "lsu.commands": ["accuracy = lsu_accuracy.accuracy_cli:register"],
    },
)
