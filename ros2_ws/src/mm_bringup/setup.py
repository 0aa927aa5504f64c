from glob import glob

from setuptools import find_packages, setup

package_name = 'mm_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/mm_bringup']),
        ('share/mm_bringup', ['package.xml']),
        ('share/mm_bringup/config', glob('config/*')),
        ('share/mm_bringup/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mm developers',
    maintainer_email='mm@example.org',
    description='Bringup of the mm graph: configs, launch files, the rosbag2-compatible MCAP recorder and player, topic and bag tools, the demo and benchmarks.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'recorder = mm_bringup.recorder_node:main',
            'player = mm_bringup.player_node:main',
            'topic = mm_bringup.topic_tool:main',
            'bag = mm_bringup.bag_tool:main',
            'ros2 = mm_bringup.ros2_cli:main',
            'demo = mm_bringup.demo:main',
            'wheeled_container = mm_bringup.wheeled_container:main'
        ],
    },
)
