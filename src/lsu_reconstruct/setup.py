from setuptools import find_packages, setup

package_name = "lsu_reconstruct"

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
    description="Stereo model, epipolar matching, triangulation, PointCloud2 codec and the stereo_matcher node.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": ["stereo_matcher = lsu_reconstruct.node:main"],
        "lsu.nodes": ["stereo_matcher = lsu_reconstruct.node:StereoMatcherNode"],
        "lsu.commands": ["reconstruct = lsu_reconstruct.cli:register"],
    },
)
