"""Packaging for the sep_control ROS 2 (ament_python) package of sep."""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'sep_control'
here = os.path.dirname(os.path.abspath(__file__))


def _rel_glob(pattern):
    """Files matching ``pattern`` (relative to this file), as paths relative to it."""
    return sorted(os.path.relpath(p, here) for p in glob(os.path.join(here, pattern)))


data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]
_config = _rel_glob(os.path.join('config', '*.yaml'))
if _config:
    data_files.append(('share/' + package_name + '/config', _config))

setup(
    name=package_name,
    version='0.7.0',
    packages=find_packages(exclude=['test']),
    data_files=data_files,
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='sep team',
    maintainer_email='sep@example.com',
    description='Data-driven LQG design (trajectory optimization, TV-ERA, LQR/KF), ROS 2 controller nodes and tools (sep).',
    license='Apache-2.0',
    python_requires='>=3.10',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'lqr = sep_control.ros.lqr_node:main',
            'lqg = sep_control.ros.lqg_node:main',
            'design = sep_control.cli.design:main',
            'evaluate = sep_control.cli.evaluate:main',
            'validate = sep_control.cli.validate:main',
            'record = sep_control.ros.record_node:main',
            'analyze = sep_control.cli.analyze:main',
            'demo = sep_control.cli.demo:main',
        ],
    },
)
