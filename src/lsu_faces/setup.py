from setuptools import find_packages, setup

package_name = "lsu_faces"

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
    description="Meshing, smoothing, texture, renders, nose tip, spherical embedding, face gallery and the face_processor node.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": ["face_processor = lsu_faces.node:main"],
        "lsu.nodes": ["face_processor = lsu_faces.node:FaceProcessorNode"],
        "lsu.commands": ["face = lsu_faces.cli:register"],
    },
)
