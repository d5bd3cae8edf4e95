"""Packaging beyond pyproject.toml: the top-level ``schemas/`` and ``reports/`` in the wheel.

The repository keeps them beside ``pipeline/``; a wheel carries them inside the
package as ``pipeline/_data/schemas`` and ``pipeline/_data/reports``, where
:mod:`pipeline.resources` looks when no checkout is beside the package.
"""

from setuptools import find_packages, setup

DATA = {"pipeline._data.schemas": "schemas", "pipeline._data.reports": "reports"}

setup(
    packages=find_packages(include=["pipeline", "pipeline.*"]) + list(DATA),
    package_dir={"": ".", **DATA},
    package_data={
        "pipeline": ["robots/*.urdf", "py.typed"],
        "pipeline._data.schemas": ["*.json", "ros2/*/msg/*.msg"],
        "pipeline._data.reports": ["*.j2", "*.css"],
    },
)
