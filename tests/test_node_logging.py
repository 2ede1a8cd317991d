"""A node's log lines (ros.logging.NodeLogger): the record rclpy's own logger writes, severity, name, message and the
caller's function, file and line, with and without rclpy's filters; levels below the logger's are not written."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import rclpy
    from rclpy.node import Node

    from lego_loam_py.ros.node_base import LegoLoamNode

    rclpy.init()
    node = LegoLoamNode('logging_check')

    def caller():
        node.get_logger().info('plain info')  # line 11
        node.get_logger().warning('plain warning')  # line 12
        node.get_logger().error('filtered', throttle_duration_sec=1.0)  # line 13
        Node.get_logger(node).info('rclpy itself')  # line 14
        node.get_logger().debug('below the level')

    caller()
    node.destroy_node()
    rclpy.shutdown()
    """
)


def test_node_log_lines_name_the_caller_as_rclpy_does(tmp_path, ros_domain):
    script = tmp_path / 'log_lines.py'
    script.write_text(SCRIPT)
    env_format = '[{severity}] [{name}]: {message} @ {function_name} {file_name}:{line_number}'
    done = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, 'RCUTILS_CONSOLE_OUTPUT_FORMAT': env_format, 'RCUTILS_COLORIZED_OUTPUT': '0'},
    )
    assert done.returncode == 0, done.stderr
    lines = [line for line in (done.stdout + done.stderr).splitlines() if '[logging_check]' in line]
    assert lines == [
        f'[INFO] [logging_check]: plain info @ caller {script}:11',
        f'[WARN] [logging_check]: plain warning @ caller {script}:12',
        f'[ERROR] [logging_check]: filtered @ caller {script}:13',
        f'[INFO] [logging_check]: rclpy itself @ caller {script}:14',
    ], lines
