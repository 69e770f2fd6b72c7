"""Geometry of the default seat (gmsh ``.geo`` files), shipped as package data.

Installed as ``hailstorm.meshes`` so that :func:`hailstorm.precompute.geometry.default_seat_path`
finds it both from a source checkout and from an installed wheel.
"""
