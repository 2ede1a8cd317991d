"""lego_loam_py: LeGO-LOAM lidar odometry and mapping for ROS 2, in Python (ament_python package)."""

import os
from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = 'lego_loam_py'
HERE = os.path.dirname(os.path.abspath(__file__))


def _files(pattern):
    return sorted(os.path.relpath(p, HERE) for p in glob(os.path.join(HERE, pattern)))


# Installed next to the Python package (install.sh links the same list for editable installs).
DATA_FILES = [
    # ament index marker and manifest: `ros2 run` and get_package_share_directory find the package.
    ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
    (f'share/{PACKAGE}', ['package.xml']),
    (f'share/{PACKAGE}/config', _files('config/*.yaml') + _files('config/*.xml') + _files('config/*.rviz')),
    (f'share/{PACKAGE}/launch', _files('launch/*.launch.py')),
]


def _native(module: str, source: str, vectorised: bool = False, headers: tuple[str, ...] = ()) -> Extension:
    """An optional C extension ``lego_loam_py.core.<module>`` from ``core/native/<source>``: IEEE arithmetic as
    written (no fast math, no fused multiply-adds), since the kernels reproduce NumPy's and libm's results bit for
    bit. Each module that uses one keeps its NumPy version for when it cannot be built. ``vectorised``: loops over
    arrays also run several elements at a time (-O3; -fno-trapping-math lets a comparison choose between two
    values without a branch: it changes no value, only the assumption that a floating-point operation may trap).
    ``headers``: the ``core/native`` headers it includes (rebuilt when they change, shipped with the sources)."""
    # (-fno-fast-math turns trapping maths back on: the order matters.)
    optimise = ['-O3', '-fno-trapping-math'] if vectorised else ['-O2']
    return Extension(
        f'{PACKAGE}.core.{module}',
        [f'{PACKAGE}/core/native/{source}'],
        depends=[f'{PACKAGE}/core/native/{header}' for header in headers],
        extra_compile_args=['-fno-fast-math', '-ffp-contract=off', *optimise],
        libraries=['m'],
        optional=True,
    )


EXT_MODULES = [
    # libm's atan2f on arrays, and the range-image columns decided mostly without it (parity/)
    _native('_libm_compat', 'libm_compat.c', vectorised=True),
    # featureAssociation's inner loops (odometry/, imu/buffer.py)
    _native('_feature_kernels', 'feature_kernels.c', headers=('sweep_jacobian.h',)),
    # the sweep-start odometry's Gauss-Newton blocks (odometry/laser_odometry.py; its own 3x3 linear algebra)
    _native('_odometry_kernels', 'odometry_kernels.c', headers=('sweep_jacobian.h', 'symmetric_eigen.h')),
    _native('_voxel_kernels', 'voxel_kernels.c', headers=('radix_sort.h',)),  # the voxel filter in one pass (voxel.py)
    # segment components, ground walk, the laser order's passes (projection/)
    _native('_projection_kernels', 'projection_kernels.c', vectorised=True),
    # plane and line fits through neighbourhoods, the grid's neighbour searches (geometry.py)
    _native('_geometry_kernels', 'geometry_kernels.c', headers=('symmetric_eigen.h',)),
    # the occupancy grid's disk update and a keyframe's classification (mapping/occupancy_grid.py, occupancy_ground.py)
    _native('_occupancy_kernels', 'occupancy_kernels.c', vectorised=True, headers=('radix_sort.h',)),
]

CONSOLE_SCRIPTS = [
    f'{PACKAGE} = {PACKAGE}.cli:main',
    f'imageProjection = {PACKAGE}.ros.image_projection_node:main',
    f'featureAssociation = {PACKAGE}.ros.feature_association_node:main',
    f'mapOptimization = {PACKAGE}.ros.map_optimization_node:main',
    f'transformFusion = {PACKAGE}.ros.transform_fusion_node:main',
    f'legoLoam = {PACKAGE}.ros.composed_node:main',
]

if __name__ == '__main__':
    setup(
        name=PACKAGE,
        version='0.1.0',
        description='LeGO-LOAM lidar odometry and mapping for ROS 2, in Python: a drop-in replacement for '
        'the C++ original',
        license='BSD-3-Clause',
        python_requires='>=3.10',
        packages=find_packages(include=[PACKAGE, f'{PACKAGE}.*']),
        data_files=DATA_FILES,
        ext_modules=EXT_MODULES,
        # ROS dependencies (rclpy, messages) come from ROS itself and are declared in package.xml.
        install_requires=['setuptools', 'numpy', 'scipy', 'pyyaml', 'rosbags', 'tqdm', 'threadpoolctl'],
        zip_safe=True,
        entry_points={'console_scripts': CONSOLE_SCRIPTS},
    )
