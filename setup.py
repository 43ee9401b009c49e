"""The package layout for setuptools (everything else is in pyproject.toml).

The top-level folders are the `shiftkit.*` packages (`pipelines/` is `shiftkit.pipelines`, ...);
every package below them is found, so a new subpackage (an env family folder) needs no edit here.
pyproject.toml cannot say this itself: setuptools' package finder names packages after their
folders and cannot put them under `shiftkit.`.
"""

from setuptools import find_packages, setup

TOP_LEVEL = ("datasets", "pipelines", "transforms", "policies", "envs", "cards", "app")

setup(
    package_dir={f"shiftkit.{folder}": folder for folder in TOP_LEVEL},
    packages=[f"shiftkit.{p}" for p in find_packages(include=[*TOP_LEVEL, *(f"{t}.*" for t in TOP_LEVEL)])],
)
