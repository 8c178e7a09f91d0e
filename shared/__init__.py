"""fleetmap.shared: what agents and the merger both use.

- :mod:`fleetmap.shared.core`: the pure algorithms (numpy in, numpy out).
- :mod:`fleetmap.shared.io`: files, the bus, recordings.
- :mod:`fleetmap.shared.config` (the one typed configuration) and :mod:`fleetmap.shared.errors`.
"""
