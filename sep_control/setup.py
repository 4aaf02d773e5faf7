"""Packaging for the sep_control ROS 2 (ament_python) package of sep.

Built by colcon (`make build`: the ros2-run layout in ros_ws/install) or by pip without ROS
(`pip install ./sep_plant ./sep_estimator ./sep_control`: the offline tools).  The version is a
literal copy of ``sep_plant.__version__`` (readable without importing; a test checks the copies).
"""
import os
from glob import glob

from setuptools import find_packages, setup

package_name = 'sep_control'
VERSION = '0.8.0'  # = sep_plant.__version__
here = os.path.dirname(os.path.abspath(__file__))


def _rel_glob(pattern):
    """Files matching ``pattern`` (relative to this file), as paths relative to it."""
    return sorted(os.path.relpath(p, here) for p in glob(os.path.join(here, pattern)))


data_files = [
    ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
    ('share/' + package_name, ['package.xml']),
]
# The controller nodes' parameter files (--params-file), under share/<pkg>/config.
_config = _rel_glob(os.path.join('config', '*.yaml'))
if _config:
    data_files.append(('share/' + package_name + '/config', _config))

setup(
    name=package_name,
    version=VERSION,
    packages=find_packages(exclude=['test']),
    data_files=data_files,
    # What the package imports at run time; never rclpy or ROS messages (they come from ROS:
    # package.xml), so that the offline tools (`sep design | evaluate | validate`) and Dask
    # workers install without ROS.  lz4 and backports.zstd: bag chunk decompression.
    install_requires=[
        'sep_plant==' + VERSION, 'sep_estimator==' + VERSION,
        'numpy', 'scipy', 'PyYAML', 'matplotlib', 'rosbags', 'tqdm', 'threadpoolctl', 'osqp',
        'lz4', 'backports.zstd; python_version < "3.14"',
    ],
    zip_safe=True,
    maintainer='sep team',
    maintainer_email='sep@example.com',
    description='Data-driven LQG design (trajectory optimization, TV-ERA, LQR/KF), ROS 2 controller nodes and tools (sep).',
    license='Apache-2.0',
    python_requires='>=3.10',
    extras_require={'dask': ['dask[distributed]'], 'test': ['pytest', 'mcap']},
    entry_points={
        'console_scripts': [
            'sep = sep_control.cli.main:main',
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
