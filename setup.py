"""Maps the repository's top-level folders into one import name, ``steerlab``.

The folders ``app/``, ``analysis/``, ``hardware/``, ``protocols/`` and ``benchmarks/`` stay
where they are in the repository; installed, they become ``steerlab.app``, ``steerlab.analysis``
and so on, and nothing else is added to site-packages. Everything else is in pyproject.toml.
"""

from setuptools import find_packages, setup

SUBPACKAGES = ("app", "analysis", "hardware", "protocols", "benchmarks")

packages = ["steerlab"]
package_dir = {"steerlab": "steerlab"}
for top in SUBPACKAGES:
    package_dir[f"steerlab.{top}"] = top
    packages += [f"steerlab.{top}"] + [f"steerlab.{top}.{p}" for p in find_packages(top)]

setup(packages=packages, package_dir=package_dir)
