"""fleetmap.shared: what agents and the merger both use.

Geometry, segment extraction (paper III-D), integration of two segment maps (paper III,
Algorithms 1-5), the typed configuration, map and scan file formats, and the error hierarchy.
Everything here is pure (numpy in, numpy out) except the small readers and writers in
``scans`` and ``mapfile``.
"""
