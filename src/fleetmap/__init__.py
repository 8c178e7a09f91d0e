"""fleetmap: one global segment map for a fleet of robots that know nothing of where they are.

Following Amigoni, Gasparini & Gini, "Building Segment-Based Maps Without Pose Information"
(Proc. IEEE 94(7), 2006). The library lives in subpackages:

- ``fleetmap.shared``: geometry, segment extraction, integration and fusion, config, file formats
- ``fleetmap.merger``: merging many maps (the paper's known-order merges, and the pose graph for an unknown order)
- ``fleetmap.agents``: the robot agent
- ``fleetmap.scenarios``: simulated worlds, the laser simulator and ground-truth metrics
"""

from importlib.metadata import version

__version__ = version("fleetmap")
"""The installed package's version (``pyproject.toml`` holds it)."""
