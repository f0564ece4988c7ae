from setuptools import find_packages, setup

package_name = "lsu_tools"

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
    description="The lsu command: launch, run, graph introspection (node, topic, service, param), doctor, demo, self-test nodes.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "lsu = lsu_tools.cli:main",
            "selftest_talker = lsu_tools.selftest:talker_main",
            "selftest_listener = lsu_tools.selftest:listener_main",
        ],
        # node classes for `lsu run` (all nodes in one process); name = executable name
        "lsu.nodes": [
            "selftest_talker = lsu_tools.selftest:SelftestTalker",
            "selftest_listener = lsu_tools.selftest:SelftestListener",
        ],
        # every `lsu` subcommand, this package's own included: lsu_tools.cli imports none of them
        "lsu.commands": [
            "launch = lsu_tools.cli:register",
            "graph = lsu_tools.graph:register",
            "doctor = lsu_tools.doctor:register",
            "demo = lsu_tools.demo:register",
        ],
    },
)
