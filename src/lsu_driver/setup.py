from setuptools import find_packages, setup

package_name = "lsu_driver"

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
    description="GP32 serial protocol codec, pyserial client, GP32 emulator (pty) and the gp32_driver node.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "gp32_driver = lsu_driver.node:main",
            "gp32_emulator = lsu_driver.emulator_node:main",
        ],
        "lsu.nodes": [
            "gp32_driver = lsu_driver.node:Gp32DriverNode",
            "gp32_emulator = lsu_driver.emulator_node:Gp32EmulatorNode",
        ],
        "lsu.commands": [
            "gp32 = lsu_driver.cli:register",
        ],
    },
)
