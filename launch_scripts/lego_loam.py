#!/usr/bin/env python3
"""Start LeGO-LOAM: the four lego_loam_py nodes as separate, supervised processes.

The launch file of installs without ``ros2 launch`` (ROS 2 from PyPI wheels); run it with the venv's Python:

    .venv/bin/python launch_scripts/lego_loam.py                          # nodes only, until Ctrl-C
    .venv/bin/python launch_scripts/lego_loam.py --bag bags/campus_8s     # + player (sim time), stops at the end
    .venv/bin/python launch_scripts/lego_loam.py --bag B --record -o out_bag --stats-dir stats
    .venv/bin/python launch_scripts/lego_loam.py --params-file my.yaml -p sensor.imu_topic:=""

It is ``lego_loam_py launch`` (``--help`` lists every option; see lego_loam_py/launch.py). With a full ROS 2
install use ``ros2 launch lego_loam_py lego_loam.launch.py`` instead.
"""

import sys

try:
    from lego_loam_py.launch import main_argv
except ImportError as exc:  # not the venv's Python
    sys.exit(
        f"lego_loam.py: cannot import lego_loam_py ({exc}); run it with the venv's Python, e.g. "
        f'.venv/bin/python launch_scripts/lego_loam.py (after bash install.sh)'
    )

if __name__ == '__main__':
    sys.exit(main_argv())
