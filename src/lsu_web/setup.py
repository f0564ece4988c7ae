from setuptools import find_packages, setup

package_name = "lsu_web"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["py.typed", "static/*", "static/vendor/three/*", "static/vendor/three/addons/*/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="LSU developers",
    maintainer_email="lsu-dev@example.org",
    description="The web page for the person at the scanner (`lsu web`): FastAPI + uvicorn, one more client of the "
                "graph; static page with vendored three.js.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "web_server = lsu_web.cli:main",
        ],
        "lsu.commands": [
            "web = lsu_web.cli:register",
        ],
    },
)
