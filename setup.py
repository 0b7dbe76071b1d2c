"""
Build steps that setup.cfg cannot declare (metadata and dependencies stay in setup.cfg):
the RL Zoo start-up files go to the top of site-packages, and ``hyperparams/*.yml`` into the package.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

# Both run sb3_dacerf_zoo_hook.install() at interpreter start: a .pth import line up to Python 3.14, and the
# PEP 829 entry point from 3.15 on (where a matching .start file turns the .pth import line off)
STARTUP_FILES = {
    "sb3_dacerf_zoo.pth": "import sb3_dacerf_zoo_hook; sb3_dacerf_zoo_hook.install()\n",
    "sb3_dacerf_zoo.start": "sb3_dacerf_zoo_hook:install\n",
}


class BuildPyWithZooHook(build_py):
    """``build_py`` that also writes the RL Zoo start-up files and copies the RL Zoo YAML files into the package."""

    def run(self) -> None:
        super().run()
        if self.editable_mode:
            # An editable wheel is made of install_lib; sb3_dacerf.zoo finds the YAML files in the source tree
            target = Path(self.get_finalized_command("install").install_lib)
        else:
            target = Path(self.build_lib)
            hyperparams_dir = target / "sb3_dacerf" / "hyperparams"
            hyperparams_dir.mkdir(parents=True, exist_ok=True)
            for path in sorted(Path("hyperparams").glob("*.yml")):
                shutil.copyfile(path, hyperparams_dir / path.name)
        for name, content in STARTUP_FILES.items():
            (target / name).write_text(content, encoding="utf-8")


setup(cmdclass={"build_py": BuildPyWithZooHook})
