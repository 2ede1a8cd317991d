"""The rclpy nodes and what only they need (message conversions, QoS, TF, the node base)."""

import sys

from lego_loam_py.blas import one_blas_thread

one_blas_thread()  # (before a node imports NumPy)

# rosidl_generator_py's package imports its code generator (rosidl_parser's grammar, lark, empy) whenever a message's
# type support is first loaded, inside a try/except ImportError meant for installs without it. A node never
# generates code: the generator's module is marked absent (None in sys.modules), 30 ms of CPU off each start-up.
sys.modules.setdefault('rosidl_generator_py.generate_py_impl', None)
