"""pip install of the numpy core and the ``sonar-ring`` command, without ROS.

ROS users build the package with colcon (CMakeLists.txt), which also generates
the ``sonar_ring.msg`` interfaces; this file serves notebooks and analysis.
"""

from pathlib import Path

from setuptools import find_packages, setup

here = Path(__file__).parent
config_files = {}
for path in sorted((here / "config").rglob("*")):
    if path.is_file():
        folder = Path("share/sonar_ring") / path.parent.relative_to(here)
        config_files.setdefault(str(folder), []).append(str(path.relative_to(here)))

setup(
    name="sonar_ring",
    version="0.1.0",
    description="Sonar ring perception: plane / corner / edge landmarks from times of flight",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["sonar_ring", "sonar_ring.*"]),
    data_files=sorted(config_files.items()),
    install_requires=["numpy>=1.24", "numba>=0.60", "pyyaml>=6", "gtsam>=4.2", "pyserial>=3.5"],
    extras_require={
        "plot": ["matplotlib>=3.7"],
        "bag": ["rosbags>=0.10", "tqdm>=4.66"],
    },
    entry_points={"console_scripts": ["sonar-ring = sonar_ring.cli:run"]},
)
