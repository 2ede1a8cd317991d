"""What the tests and the benchmarks share to run the nodes and feed them: a ROS domain of their own
(:mod:`.domains`), spinning and reading the nodes (:mod:`.nodes`), messages restamped (:mod:`.messages`) or
malformed field by field (:mod:`.malformed`), a bag with a stretch cut out (:mod:`.bags`), a bag player that
restamps laps (:mod:`.feeder`, ``python -m lego_loam_py.testing.feeder``) and a process's memory (:mod:`.measure`).

Nothing of the pipeline imports it.
"""
