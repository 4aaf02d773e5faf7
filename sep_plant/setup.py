"""Packaging for the sep_plant ROS 2 (ament_python) package of sep."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'sep_plant'
here = os.path.dirname(os.path.abspath(__file__))


def _rel_glob(pattern):
    """Files matching ``pattern`` (relative to this file), as paths relative to it."""
    return sorted(os.path.relpath(p, here) for p in glob(os.path.join(here, pattern)))


data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]
_scenarios = _rel_glob(os.path.join('scenarios', '*.yaml'))
if _scenarios:
    data_files.append(('share/' + package_name + '/scenarios', _scenarios))

setup(
    name=package_name,
    version='0.7.0',
    packages=find_packages(exclude=['test']),
    data_files=data_files,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='sep team',
    maintainer_email='sep@example.com',
    description='The plant protocol, built-in black-box plants (1-D slab, 2-D plate, 3-D block, Allen-Cahn), scenarios, the topic contract and the ROS 2 plant node (sep).',
    license='Apache-2.0',
    python_requires='>=3.10',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'plant = sep_plant.ros.plant_node:main',
        ],
    },
)
