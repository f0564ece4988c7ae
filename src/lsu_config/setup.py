import os

from setuptools import find_packages, setup

package_name = "lsu_config"


def data_files_of(package: str, folder: str) -> list:
    """Every file under ``package/folder`` (a link to the repository's config/), relative to the package."""
    root = os.path.join(package, folder)
    found = []
    for dirpath, _dirs, files in os.walk(root, followlinks=True):
        found += [os.path.relpath(os.path.join(dirpath, f), package) for f in files if not f.endswith(".pyc")]
    return sorted(found)


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["py.typed", *data_files_of(package_name, "data")]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="LSU developers",
    maintainer_email="lsu-dev@example.org",
    description="LSU configuration (launch files, parameters, calibration, profiles, DDS profile) as package data.",
    license="Apache-2.0",
    tests_require=["pytest"],
)
