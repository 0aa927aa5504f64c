from glob import glob

from setuptools import find_packages, setup

package_name = 'mm_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/mm_sim']),
        ('share/mm_sim', ['package.xml']),
        ('share/mm_sim/config', glob('config/*')),
        ('share/mm_sim/layouts', glob('layouts/*.yaml')),
        ('share/mm_sim/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mm developers',
    maintainer_email='mm@example.org',
    description='Simulators of the mm experiments: a differential-drive robot with five proximity sensors near a wall, and a 2-joint planar arm seen by a camera.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'wheeled_sim = mm_sim.wheeled_sim_node:main',
            'arm_sim = mm_sim.arm_sim_node:main'
        ],
    },
)
