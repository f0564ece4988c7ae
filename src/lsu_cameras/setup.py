from setuptools import find_packages, setup

package_name = "lsu_cameras"

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
    description="Stereo camera sources (v4l2, image folders; more as lsu.camera_sources plug-ins, e.g. lsu_sim), stereo calibration and the stereo_camera node.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": ["stereo_camera = lsu_cameras.node:main"],
        "lsu.nodes": ["stereo_camera = lsu_cameras.node:StereoCameraNode"],
        "lsu.commands": ["cameras = lsu_cameras.cli:register"],
    },
)
