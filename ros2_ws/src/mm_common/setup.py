from glob import glob

from setuptools import find_packages, setup

package_name = 'mm_common'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/mm_common']),
        ('share/mm_common', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mm developers',
    maintainer_email='mm@example.org',
    description='Shared helpers for the mm nodes: the Jazzy main() pattern, parameter declaration with descriptors, MCAP/rosbag2 schema tools.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            
        ],
    },
)
