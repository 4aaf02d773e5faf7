"""Packaging for the sep_estimator ROS 2 (ament_python) package of sep."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'sep_estimator'
here = os.path.dirname(os.path.abspath(__file__))


def _rel_glob(pattern):
    """Files matching ``pattern`` (relative to this file), as paths relative to it."""
    return sorted(os.path.relpath(p, here) for p in glob(os.path.join(here, pattern)))


data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]

setup(
    name=package_name,
    version='0.7.0',
    packages=find_packages(exclude=['test']),
    data_files=data_files,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='sep team',
    maintainer_email='sep@example.com',
    description='Time-varying Kalman filter on the identified ROM and its ROS 2 estimator node (sep).',
    license='Apache-2.0',
    python_requires='>=3.10',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'estimator = sep_estimator.ros.estimator_node:main',
        ],
    },
)
