"""Packaging for the sep_plant ROS 2 (ament_python) package of sep.

Built by colcon (`make build`: the ros2-run layout in ros_ws/install) or by pip without ROS
(`pip install ./sep_plant ./sep_estimator ./sep_control`: the offline tools).  The version is a
literal copy of ``sep_plant.__version__`` (readable without importing; a test checks the copies).
"""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'sep_plant'
VERSION = '0.8.0'  # = sep_plant.__version__
here = os.path.dirname(os.path.abspath(__file__))


def _rel_glob(pattern):
    """Files matching ``pattern`` (relative to this file), as paths relative to it."""
    return sorted(os.path.relpath(p, here) for p in glob(os.path.join(here, pattern)))


data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]
# Shipped scenarios and the nodes' parameter files (--params-file), under share/<pkg>/.
for _sub in ('scenarios', 'config'):
    _files = _rel_glob(os.path.join(_sub, '*.yaml'))
    if _files:
        data_files.append(('share/' + package_name + '/' + _sub, _files))

setup(
    name=package_name,
    version=VERSION,
    packages=find_packages(exclude=['test']),
    data_files=data_files,
    # What the package imports at run time; never rclpy or ROS messages (they come from ROS:
    # package.xml), so that the offline tools install without ROS.
    install_requires=['numpy', 'scipy', 'PyYAML', 'threadpoolctl'],
    zip_safe=True,
    maintainer='sep team',
    maintainer_email='sep@example.com',
    description='The plant protocol, built-in black-box plants (1-D slab, 2-D plate, 3-D block, Allen-Cahn), scenarios, the topic contract and the ROS 2 plant node (sep).',
    license='Apache-2.0',
    python_requires='>=3.10',
    # fmpy: the fmu plant (sep_plant.plants.fmu), imported only when an FMU is opened
    extras_require={'test': ['pytest'], 'fmu': ['fmpy']},
    entry_points={
        'console_scripts': [
            'plant = sep_plant.ros.plant_node:main',
        ],
    },
)
