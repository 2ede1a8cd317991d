"""Decoders of raw sensor data: VLP-16 and Ouster packets, and the pcap captures that hold them.

They turn a recording into point clouds for ``lego_loam_py convert`` (:mod:`lego_loam_py.bag.convert`); the
pipeline itself (:mod:`lego_loam_py.core`) never uses them. Pure numpy, no ROS.
"""
