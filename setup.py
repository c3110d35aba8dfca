"""Ships the checkout's sql/ and etc/ inside the package (gwc/data/), so an installed gwc can set up a
cell: the top level keeps sql/ and etc/ where they are, and setuptools' package data cannot reach
outside a package. Everything else is in pyproject.toml."""

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

SHIPPED = ("sql", "etc")


class BuildPyWithData(build_py):
    def run(self) -> None:
        super().run()
        for folder in SHIPPED:
            self.copy_tree(folder, str(Path(self.build_lib) / "gwc" / "data" / folder))


setup(cmdclass={"build_py": BuildPyWithData})
