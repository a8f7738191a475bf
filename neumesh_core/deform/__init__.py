"""Deformations of a field's scaffold driven by a few vertices (docs/addon.md, *ARAP deform*).

- :class:`ArapSolver`: as-rigid-as-possible deformation with anchor and handle vertex sets, factorised
  once per set; :meth:`ArapSolver.solve` per handle move (optionally on a decimated cage, the preview
  resolution, carried to every vertex).
- :func:`arap`: the one-call form for scripts: deform a field from its rest pose by handle transforms.
- :class:`ArapTerms`: the ARAP energy's pieces, shared with the swap alignment's non-rigid ICP.
"""
from .arap import ArapConfig, ArapResult, ArapSolver, ArapTerms, ConstrainedArap, arap, edge_weights
from .cage import Cage, build_cage
from .rotations import polar_rotations, polar_rotations_reference

__all__ = ["ArapConfig", "ArapResult", "ArapSolver", "ArapTerms", "Cage", "ConstrainedArap", "arap", "build_cage",
           "edge_weights", "polar_rotations", "polar_rotations_reference"]
