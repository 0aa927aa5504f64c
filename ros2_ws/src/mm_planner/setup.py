from glob import glob

from setuptools import find_packages, setup

package_name = 'mm_planner'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/mm_planner']),
        ('share/mm_planner', ['package.xml']),
        ('share/mm_planner/config', glob('config/*')),
        ('share/mm_planner/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mm developers',
    maintainer_email='mm@example.org',
    description='Controllers of mm: exploration and sensor-switching Jacobian control for the wheeled robot, dynamic-programming planner for the arm.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'switching_controller = mm_planner.switching_controller_node:main',
            'dp_planner = mm_planner.dp_planner_node:main'
        ],
    },
)
