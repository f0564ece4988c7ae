from setuptools import find_packages, setup

package_name = "lsu_view"

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
    description="Live view: the foxglove_bridge node (Foxglove WebSocket server passing the graph's CDR through) "
                "and `lsu view`.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "foxglove_bridge = lsu_view.node:main",
        ],
        "lsu.nodes": [
            "foxglove_bridge = lsu_view.node:FoxgloveBridgeNode",
        ],
        "lsu.commands": [
            "view = lsu_view.cli:register",
        ],
    },
)
