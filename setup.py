from glob import glob

from setuptools import find_packages
from setuptools import setup

package_name = 'landmark_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('share/' + package_name + '/rviz', glob('rviz/*.rviz')),
    ],
    # Only plain-PyPI runtime deps here. The ROS 2 packages (rclpy, *_msgs,
    # std_srvs) are declared in package.xml and come from apt/rosdep on a ROS
    # machine or from requirements-ros.txt in the dev venv; listing them here
    # would pull a second rclpy into an apt-installed Jazzy. landmark_bag reads and
    # writes bags with rosbags and shows progress with tqdm (pinned as in
    # requirements-dev.txt: a new rosbags may change the bag format it writes). numba
    # compiles the split-CI fold (fusion/compiled.py; the numpy fold serves without it).
    install_requires=['numpy', 'scipy', 'pyyaml', 'rosbags==0.11.9', 'tqdm==4.70.1',
                      'numba>=0.59'],
    extras_require={
        'plot': ['matplotlib'],
    },
    zip_safe=True,
    python_requires='>=3.10',
    maintainer='landmark_ros maintainers',
    maintainer_email='maintainers@example.com',
    description=(
        'Landmark-based perception for multi-robot teams: range-bearing observations '
        'to world-frame landmarks with covariance, multi-robot fusion.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            # One 'name = module:function' per node; keep EXPECTED_EXECUTABLES in
            # test/test_colcon_install.py in sync.
            'landmark_observer = landmark_ros.nodes.start:observer',
            'landmark_fuser = landmark_ros.nodes.start:fuser',
            'landmark_sim = landmark_ros.nodes.start:sim',
            'landmark_localizer = landmark_ros.nodes.start:localizer',
            'landmark_mrclam = landmark_ros.mrclam.cli:main',
            'landmark_bag = landmark_ros.bag.cli:main',
        ],
    },
)
