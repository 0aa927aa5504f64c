from glob import glob

from setuptools import find_packages, setup

package_name = 'mm_manifold'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/mm_manifold']),
        ('share/mm_manifold', ['package.xml']),
        ('share/mm_manifold/config', glob('config/*')),
        ('share/mm_manifold/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='mm developers',
    maintainer_email='mm@example.org',
    description='Learning nodes of mm: grid-based sensor manifold, Jacobians and virtual sensor space (Section 2); SIFT keypoint vectors, LLE/PCA embedding and collision sphere (Section 3).',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'sensor_manifold = mm_manifold.sensor_manifold_node:main',
            'image_embedding = mm_manifold.image_embedding_node:main'
        ],
    },
)
