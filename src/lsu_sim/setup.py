from setuptools import find_packages, setup

package_name = "lsu_sim"

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
    description="The simulated LSU rig: geometry, scenes and people, laser and camera physics, the ray-cast "
                "stereo renderer, the simulated camera source and `lsu render`.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        # the stereo_camera node's source "sim" (lsu_cameras never imports this package)
        "lsu.camera_sources": ["sim = lsu_sim.source:open_sim_source"],
        "lsu.commands": ["sim = lsu_sim.cli:register"],
    },
)
