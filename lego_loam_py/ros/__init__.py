"""The rclpy nodes and what only they need (message conversions, QoS, TF, the node base)."""

from lego_loam_py.blas import one_blas_thread

one_blas_thread()  # (before a node imports NumPy)
