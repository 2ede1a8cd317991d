"""Lidar + IMU simulator: ray casting against procedural triangle meshes, with ground truth and labels.

ROS-free like the core (numpy, scipy, open3d); bags are written through :mod:`lego_loam_py.bag.io`.

* :mod:`.scene` -- materials, terrain height fields, primitive meshes, the ray-casting scene with
  per-triangle instance labels and materials.
* :mod:`.trajectory` -- continuous sensor trajectories (periodic splines, terrain-following vehicles,
  walking) with consistent velocities, accelerations and body angular rates.
* :mod:`.lidar` -- the spinning lidar model (sensor presets, firing order, range noise, dropped returns,
  intensity), one ray cast per sweep.
* :mod:`.imu` -- the IMU model (orientation, body angular velocity, specific force, noise and bias).
* :mod:`.scenarios` -- the seeded scenarios: ``campus``, ``forest``, ``corridor``, ``aggressive``.
* :mod:`.output` -- sidecar files beside a bag (ground truth, labels, parameters, note).
* :mod:`.simulator` -- the driver writing a bag, and the on-demand cache of long scenarios.
* :mod:`.render` -- top-down PNG of a scan of any bag (``lego_loam_py view``).
* :mod:`.cli` -- ``lego_loam_py simulate``.

Importing this package is cheap: open3d and matplotlib load only when a simulation or a view runs.
"""
